"""models.inference: the folded Encoder equals the model, threads, input checks, bfloat16."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import Encoder, bf16_supported, top1_agreement
from tests.models.helpers import CONFIGS, clouds, trained_like


@pytest.mark.parametrize(
    ("name", "tile"),
    [(name, 1024) for name in sorted(CONFIGS)] + [("paper-narrow", 100), ("max", 100)],
)
def test_encoder_matches_model(name: str, tile: int) -> None:
    cfg = CONFIGS[name]
    model = trained_like(cfg)
    x = clouds(5, seed=2)
    with torch.no_grad():
        want = model(x).numpy()
    enc = Encoder(model, cfg, batch_size=2, point_tile=tile)
    got = enc.embed(x)
    assert got.shape == (5, cfg.output_dim) and got.dtype == np.float32
    assert np.abs(got - want).max() < 1e-5
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    assert enc.dim == cfg.output_dim
    assert model.training is False  # the encoder leaves the model's mode as it was


def _narrow_case(n: int, seed: int) -> tuple:
    """The narrow paper config, a model with non-trivial batch norms, ``n`` clouds and the
    model's own descriptors of them (what every encoder path must give)."""
    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    x = clouds(n, seed=seed)
    with torch.no_grad():
        want = model(x).numpy()
    return cfg, model, x, want


def test_encoder_cloud_workers_agree_and_leave_thread_count() -> None:
    """Clouds run side by side on worker threads give the model's descriptors, in batch order,
    and the workers' single intra-op thread does not leak into the calling thread."""
    cfg, model, x, want = _narrow_case(7, seed=4)
    threads = torch.get_num_threads()
    serial = Encoder(model, cfg, cloud_workers=1)
    side_by_side = Encoder(model, cfg, cloud_workers=3, batch_size=4)
    try:
        a, b = serial.embed(x), side_by_side.embed(x)
        assert side_by_side._pool is not None and serial._pool is None
        assert np.abs(a - want).max() < 1e-5 and np.abs(b - want).max() < 1e-5
        assert torch.get_num_threads() == threads
        side_by_side.close()
        assert np.abs(side_by_side.embed(x.flip(0)) - want[::-1]).max() < 1e-5
    finally:
        side_by_side.close()
    with pytest.raises(InputError, match="cloud_workers"):
        Encoder(model, cfg, cloud_workers=0)


def test_encoder_embeds_from_several_threads_at_once() -> None:
    """The server's batcher lanes call embed concurrently: every call gets its own clouds'
    descriptors, whether its clouds run on the workers or on the calling thread."""
    import threading

    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    batches = [clouds(b, seed=10 + b) for b in (1, 3, 2, 1, 5, 1)]
    with torch.no_grad():
        want = [model(x).numpy() for x in batches]
    enc = Encoder(model, cfg, cloud_workers=2)
    got: dict[int, np.ndarray] = {}
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            for _ in range(3):
                got[i] = enc.embed(batches[i])
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(batches))]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
    finally:
        enc.close()
    assert not errors
    for i, w in enumerate(want):
        assert np.abs(got[i] - w).max() < 1e-5, i
    assert enc._embedding == 0


def test_a_crowded_encoder_keeps_off_the_threads_that_share_cores() -> None:
    """While ``crowded_by`` says other work holds the cores, a lone batch (one cloud too) runs
    its clouds and its head on the single-threaded cloud workers, not on the torch thread's
    team; alone, a single cloud and the head run on the torch thread. The descriptors are the
    model's either way."""
    import threading

    cfg, model, x, want = _narrow_case(3, seed=6)
    enc = Encoder(model, cfg, cloud_workers=2)
    where: list[str] = []
    head = enc._head_products
    cloud = enc._cloud

    def head_here(*args):  # records the thread each part runs on
        where.append("head:" + threading.current_thread().name.split("_")[0])
        return head(*args)

    def cloud_here(*args):
        where.append("cloud:" + threading.current_thread().name.split("_")[0])
        return cloud(*args)

    enc._head_products = head_here
    enc._cloud = cloud_here
    try:
        for crowded, rows in ((False, [0]), (True, [0]), (True, [0, 1, 2]), (False, [0, 1, 2])):
            enc.crowded_by = lambda crowded=crowded: crowded
            where.clear()
            got = enc.embed(x[rows])
            assert np.abs(got - want[rows]).max() < 1e-5
            assert len(where) == len(rows) + 1, where  # every cloud, then the head
            if crowded:
                assert all(w.endswith("pnvlad-encoder") for w in where), where
            elif len(rows) == 1:
                assert where == ["cloud:pnvlad-torch", "head:pnvlad-torch"], where
            else:  # two clouds on the workers, the odd one and the head on the torch thread
                assert sorted(where) == sorted(
                    ["cloud:pnvlad-encoder"] * 2 + ["cloud:pnvlad-torch", "head:pnvlad-torch"]
                ), where
    finally:
        enc.close()
    assert enc._embedding == 0


def test_a_failing_pass_leaves_the_encoder_as_it_was() -> None:
    """A crowded_by that raises, or a head that raises on a worker, fails that call only: the
    count of passes in flight is back to 0 and the next call embeds."""
    cfg, model, x, want = _narrow_case(2, seed=8)
    enc = Encoder(model, cfg, cloud_workers=2)
    head = enc._head_products

    def broken_head(*args):
        raise RuntimeError("head")

    def broken_crowded():
        raise RuntimeError("crowded")

    try:
        enc.crowded_by = broken_crowded
        with pytest.raises(RuntimeError, match="crowded"):
            enc.embed(x)
        assert enc._embedding == 0
        enc.crowded_by = lambda: True
        enc._head_products = broken_head
        with pytest.raises(RuntimeError, match="head"):
            enc.embed(x)
        assert enc._embedding == 0
        enc._head_products = head
        assert np.abs(enc.embed(x) - want).max() < 1e-5
    finally:
        enc.close()


def test_encoder_accepts_single_cloud_float64_and_other_sizes() -> None:
    cfg = CONFIGS["compact"]
    model = trained_like(cfg)
    enc = Encoder(model, cfg)
    x = clouds(1, n=300).double().numpy()
    one = enc.embed(x[0])  # [N, 3] -> [1, D]
    assert one.shape == (1, cfg.output_dim)
    with torch.no_grad():
        want = model(torch.from_numpy(x).float()).numpy()
    assert np.abs(one - want).max() < 1e-5


def test_encoder_rejects_bad_points() -> None:
    cfg = CONFIGS["compact"]
    enc = Encoder(trained_like(cfg), cfg)
    with pytest.raises(InputError, match=r"\[B, N, 3\]"):
        enc.embed(np.zeros((2, 10, 4), np.float32))
    bad = np.zeros((1, 10, 3), np.float32)
    bad[0, 3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        enc.embed(bad)
    with pytest.raises(InputError, match="dtype"):
        Encoder(trained_like(cfg), cfg, dtype="float16")


def test_training_mode_model_is_folded_with_running_stats() -> None:
    cfg = CONFIGS["compact"]
    model = trained_like(cfg).train()
    enc = Encoder(model, cfg)
    assert model.training  # restored
    with torch.no_grad():
        want = model.eval()(clouds(2)).numpy()
    assert np.abs(enc.embed(clouds(2)) - want).max() < 1e-5


@pytest.mark.skipif(not bf16_supported(), reason="CPU without native bfloat16")
def test_bfloat16_paper_head_at_batch_24() -> None:
    """The paper head (65,536 -> 256) in bfloat16 for 24 clouds: torch 2.13's bfloat16 F.linear
    of that shape dies with SIGFPE, so the encoder must not route bfloat16 through it."""
    cfg = ModelConfig.paper()
    torch.manual_seed(0)
    enc = Encoder(build_model(cfg).eval(), cfg, dtype="bfloat16")
    out = enc.embed(clouds(24, n=64, seed=1))
    assert out.shape == (24, 256) and np.allclose(np.linalg.norm(out, axis=1), 1, atol=1e-3)


@pytest.mark.skipif(not bf16_supported(), reason="CPU without native bfloat16")
def test_bfloat16_path_and_auto_self_check() -> None:
    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    x = clouds(6, seed=3)
    ref = Encoder(model, cfg).embed(x)
    low = Encoder(model, cfg, dtype="bfloat16").embed(x)
    cos = (ref * low).sum(1)
    assert cos.min() > 0.99 and np.abs(low - ref).max() > 0  # close, yet really bfloat16
    auto = Encoder(model, cfg, dtype="auto", check_points=x)
    assert auto.agreement == top1_agreement(ref, low)
    assert auto.dtype == ("bfloat16" if auto.agreement >= 0.99 else "float32")
    assert Encoder(model, cfg, dtype="auto").dtype == "float32"  # no clouds, no bfloat16


def test_top1_agreement() -> None:
    a = np.array([[0.0, 0], [1, 0], [3, 0], [10, 0]])
    assert top1_agreement(a, a) == 1.0
    b = np.array([[0.0, 0], [2.4, 0], [3, 0], [10, 0]])  # 0's neighbour: 1 -> 1 still; 1's: 0 -> 2
    assert top1_agreement(a, b) == 0.75


@pytest.mark.real_scans
def test_real_scan_descriptor_is_order_independent(real_scans: Path) -> None:
    """A real KITTI HDL-64E scan (of unknown frame: any real scan does) embeds to the same unit
    descriptor whatever the order of its points."""
    pts = np.fromfile(real_scans / "kitti00_000000.bin", dtype=np.float32).reshape(-1, 4)[:, :3]
    rng = np.random.default_rng(0)
    sub = pts[rng.choice(len(pts), 4096, replace=False)].astype(np.float64)
    sub -= sub.mean(0)
    sub /= 2 * np.linalg.norm(sub, axis=1).mean()  # mean distance 0.5, as the benchmark's G
    cfg = ModelConfig.compact()
    enc = Encoder(trained_like(cfg), cfg)
    e = enc.embed(sub)
    e_perm = enc.embed(sub[rng.permutation(4096)])
    assert np.abs(e - e_perm).max() < 1e-5
    assert abs(float(np.linalg.norm(e)) - 1.0) < 1e-6


def test_all_thread_work_runs_on_the_one_torch_thread() -> None:
    """Single clouds and the head (the steps on all of torch's threads) run on the process's
    torch thread whichever thread calls embed, so that only one OpenMP team exists (two made
    libgomp throttle its spinning: 1.4x slower embedding); batches still go to the cloud
    workers, and the descriptors are the same from every calling thread."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    seen: dict[str, set[str]] = {"cloud": set(), "head": set()}

    class Recording(Encoder):
        def _cloud(self, x, q):  # type: ignore[no-untyped-def]
            seen["cloud"].add(threading.current_thread().name)
            return super()._cloud(x, q)

        def _head_products(self, pooled, q):  # type: ignore[no-untyped-def]
            seen["head"].add(threading.current_thread().name)
            return super()._head_products(pooled, q)

    cfg = ModelConfig.compact(num_points=256)
    torch.manual_seed(0)
    enc = Recording(build_model(cfg), cfg, cloud_workers=2)
    x = clouds(3, 256, seed=1)
    here = enc.embed(x[:1])
    with ThreadPoolExecutor(1, thread_name_prefix="caller") as pool:
        there = pool.submit(enc.embed, x[:1]).result()
    assert seen["cloud"] and all(n.startswith("pnvlad-torch") for n in seen["cloud"])
    assert all(n.startswith("pnvlad-torch") for n in seen["head"])
    np.testing.assert_array_equal(here, there)
    seen["cloud"].clear()
    both = enc.embed(x[:2])  # two clouds side by side on the two cloud workers
    assert seen["cloud"] and all(n.startswith("pnvlad-encoder") for n in seen["cloud"])
    np.testing.assert_allclose(both[:1], here, atol=1e-5)
    enc.close()


def test_the_runtime_line_gives_the_embedding_threads_whatever_thread_asks() -> None:
    """``describe`` names the thread count of the thread that embeds, not the caller's: a
    server's /readyz and /info are answered from pool threads whose OpenMP count a registration
    or a cloud worker may have changed (it said 1 while the encoder ran on 2)."""
    import threading

    from pnvlad_service.models.inference import on_torch_thread
    from pnvlad_service.models.runtimes import describe

    cfg, model, x, _ = _narrow_case(2, seed=5)
    enc = Encoder(model, cfg, cloud_workers=1)
    enc.embed(x)
    embedding = on_torch_thread(torch.get_num_threads)
    before = torch.get_num_threads()
    seen: list[str] = []

    def from_a_caller_with_its_own_count() -> None:
        torch.set_num_threads(embedding + 1)  # another count than the embedding thread's
        try:
            seen.append(describe(enc))
        finally:
            torch.set_num_threads(before)  # threads started later take the last count set

    caller = threading.Thread(target=from_a_caller_with_its_own_count)
    caller.start()
    caller.join()
    assert seen == [f"torch {torch.__version__}, {embedding} threads"]


@pytest.mark.parametrize("name", ["bev", "compact"])
def test_embed_scales_average_the_descriptors_of_the_rescaled_clouds(name: str) -> None:
    """``embed_scales``: the descriptor is the unit mean of the plain encoder's descriptors of
    the cloud multiplied by each scale (computed here from the plain encoder); no scales is
    the plain encoder, and the hash of a model without them is the one it had before."""
    from pnvlad_service.models.bev import BEVNetVLAD
    from pnvlad_service.models.config import config_sha256
    from tests.models.helpers import BEV_SMALL

    plain = BEV_SMALL if name == "bev" else CONFIGS["compact"]
    model = BEVNetVLAD(plain).eval() if name == "bev" else trained_like(plain)
    scaled = plain.model_copy(update={"embed_scales": (0.8, 1.0, 1.25)})
    x = clouds(5, n=200, seed=7).numpy() * 0.7
    base = Encoder(model, plain)
    want = sum(base.embed(x * s) for s in (0.8, 1.0, 1.25))
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    got = Encoder(model, scaled).embed(x)
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert np.abs(got - base.embed(x)).max() > 1e-4  # the scales change it
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    assert config_sha256(scaled) != config_sha256(plain)  # and plain's: test_config.py
    for bad in ((0.1,), (1.0,) * 9):
        with pytest.raises(ValueError, match="embed_scales"):
            ModelConfig.model_validate({**plain.model_dump(), "embed_scales": bad})
    with pytest.raises(ValueError, match="local shape"):
        ModelConfig.compact(local_k=8, embed_scales=(1.0, 1.2))
