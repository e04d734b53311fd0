"""Encoders: configuration, the network's formulas, folded inference, checkpoints on disk."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.inference import Encoder, bf16_supported, top1_agreement
from pnvlad_service.models.pointnetvlad import build_model
from pnvlad_service.models.store import (
    config_sha256,
    load_model,
    save_model,
    weights_sha256,
)

SMALL = 256  # points per cloud in most tests


@pytest.fixture(autouse=True, scope="module")
def _one_thread() -> Iterator[None]:
    """These tensors are small: one thread avoids OpenMP barrier stalls on a busy machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def clouds(b: int, n: int = SMALL, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 3, generator=g) * 2 - 1


def trained_like(cfg: ModelConfig, seed: int = 0) -> torch.nn.Module:
    """A model whose batch norms hold non-trivial statistics and affine parameters (so folding
    them is actually exercised), in eval mode."""
    torch.manual_seed(seed)
    model = build_model(cfg)
    model.train()
    with torch.no_grad():
        for i in range(3):
            model(clouds(4, seed=100 + i))
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.3, 0.3)
        # Transform nets start at the identity; move them so their weights matter.
        for name, p in model.named_parameters():
            if name.endswith("tnet.out.weight"):
                p.normal_(0, 0.01)
    return model.eval()


CONFIGS = {
    "compact": ModelConfig.compact(num_points=SMALL),
    "paper-narrow": ModelConfig.paper(
        num_points=SMALL,
        stem_widths=(16, 16),
        trunk_widths=(16, 32, 64),
        tnet_point_widths=(16, 32, 64),
        tnet_fc_widths=(32, 16),
        cluster_size=8,
        output_dim=32,
    ),
    "port-narrow": ModelConfig.port(
        num_points=SMALL, stem_widths=(16, 16), trunk_widths=(16, 32, 64), cluster_size=8
    ),
    "max": ModelConfig.compact(arch="pointnet-max", feature_transform=True),
    "max-no-bn": ModelConfig.compact(
        arch="pointnet-max", vlad_batch_norm=False, trunk_batch_norm=False, gating=False
    ),
    "vlad-no-bn-one-layer": ModelConfig.compact(
        vlad_batch_norm=False, trunk_widths=(48,), feature_transform=True, input_transform=False
    ),
}


# -- configuration ----------------------------------------------------------------------------


def test_paper_config_is_the_published_network() -> None:
    cfg = ModelConfig.paper()
    assert cfg.arch == "pointnetvlad" and cfg.num_points == 4096
    assert cfg.stem_widths + cfg.trunk_widths == (64, 64, 64, 128, 1024)
    assert cfg.input_transform and cfg.feature_transform
    assert (cfg.cluster_size, cfg.output_dim, cfg.gating) == (64, 256, True)
    # The TensorFlow code's choices (docs/MODEL.md); the port flips all four.
    tf = (cfg.trunk_batch_norm, cfg.tnet_batch_norm, cfg.last_relu, cfg.point_l2_norm)
    assert tf == (False, True, True, True)
    port = ModelConfig.port()
    assert (port.trunk_batch_norm, port.tnet_batch_norm, port.last_relu, port.point_l2_norm) == (
        True,
        False,
        False,
        False,
    )


def test_flops_hand_count() -> None:
    cfg = ModelConfig(
        num_points=10,
        stem_widths=(4,),
        trunk_widths=(8,),
        input_transform=False,
        feature_transform=False,
        cluster_size=2,
        output_dim=3,
        gating=False,
    )
    # 10 points: 3->4 and 4->8 per point; logits 8->2 and sums 2x8 per point; fc 16->3.
    want = 2 * (10 * 3 * 4 + 10 * 4 * 8 + 10 * 8 * 2 + 10 * 2 * 8 + 16 * 3)
    assert cfg.flops_per_cloud() == want
    paper, compact = ModelConfig.paper().flops_per_cloud(), ModelConfig.compact().flops_per_cloud()
    assert 4.5e9 < paper < 4.8e9
    assert 8 < paper / compact < 12  # the compact configuration is about 10x cheaper


def test_config_validation_and_hash() -> None:
    with pytest.raises(ValueError, match="positive"):
        ModelConfig(trunk_widths=(64, 0))
    with pytest.raises(ValueError, match="extra"):
        ModelConfig(widths=(1, 2))  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="feature_transform"):
        ModelConfig(stem_widths=())
    a, b = ModelConfig.paper(), ModelConfig.paper(cluster_size=32)
    assert config_sha256(a) == config_sha256(ModelConfig.model_validate(a.model_dump(mode="json")))
    assert config_sha256(a) != config_sha256(b)
    text = json.dumps(a.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    assert config_sha256(a) == hashlib.sha256(text.encode()).hexdigest()


# -- the network ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_forward_shape_unit_norm_and_permutation_invariance(name: str) -> None:
    cfg = CONFIGS[name]
    model = trained_like(cfg)
    x = clouds(3)
    x[1, :, 2] *= 0.1  # a flat cloud: must get a clearly different descriptor
    with torch.no_grad():
        y = model(x)
        perm = torch.randperm(x.shape[1], generator=torch.Generator().manual_seed(1))
        y_perm = model(x[:, perm])
    assert y.shape == (3, cfg.output_dim) and y.dtype == torch.float32
    assert torch.allclose(y.norm(dim=1), torch.ones(3), atol=1e-6)
    assert (y - y_perm).abs().max() < 1e-5
    assert (y[0] - y[1]).abs().max() > 1e-3  # different clouds, different descriptors


def netvlad_reference(x: torch.Tensor, pool: torch.nn.Module) -> torch.Tensor:
    """NetVLAD of one cloud x [N, D] with loops over clusters and points (eval-mode BN)."""
    n, d = x.shape
    k = pool.clusters
    bn = pool.cluster_bn
    logits = x.double() @ pool.cluster_weights.double()
    logits = (logits - bn.running_mean.double()) / torch.sqrt(bn.running_var.double() + bn.eps)
    logits = logits * bn.weight.double() + bn.bias.double()
    a = torch.softmax(logits, dim=1)
    v = torch.zeros(d, k, dtype=torch.float64)
    for j in range(k):
        for i in range(n):
            v[:, j] += a[i, j] * (x[i].double() - pool.centers[:, j].double())
        v[:, j] /= v[:, j].norm()
    flat = torch.stack([v[dd, j] for dd in range(d) for j in range(k)])  # d-major, as published
    return flat / flat.norm()


def test_netvlad_matches_loop_reference() -> None:
    cfg = ModelConfig.compact(trunk_widths=(8,), cluster_size=3, output_dim=5, num_points=7)
    model = trained_like(cfg)
    pool = model.pool
    x = torch.rand(2, 7, 8)
    with torch.no_grad():
        got = pool(x)
        for b in range(2):
            flat = netvlad_reference(x[b], pool)
            y = F.linear(flat.float().unsqueeze(0), pool.fc.weight)
            y = pool.fc_bn(y)
            gates = torch.sigmoid(pool.gating.gate_bn(pool.gating.gate(y)))
            assert torch.allclose(got[b], (y * gates)[0], atol=1e-5)


def test_tf_variant_normalises_points_port_does_not() -> None:
    tf = trained_like(CONFIGS["paper-narrow"])
    port = trained_like(CONFIGS["port-narrow"])
    with torch.no_grad():
        f_tf = tf.point_features(clouds(2))
        f_port = port.point_features(clouds(2))
    assert torch.allclose(f_tf.norm(dim=2), torch.ones(2, SMALL), atol=1e-5)
    assert f_tf.min() >= 0  # ReLU after the last layer
    assert f_port.min() < 0  # no ReLU after the last layer (batch norm output)


def test_every_parameter_gets_a_gradient() -> None:
    cfg = ModelConfig.paper(
        num_points=64, stem_widths=(8, 8), trunk_widths=(8, 16), cluster_size=4, output_dim=8
    )
    model = build_model(cfg).train()
    # Transform nets start exactly at the identity (zero last layer), so nudge them first.
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("tnet.out.weight"):
                p.normal_(0, 0.01)
    y = model(clouds(6, n=64))
    (y[:3] - y[3:]).pow(2).sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_paper_config_full_size_forward() -> None:
    cfg = ModelConfig.paper()
    model = trained_like(cfg)
    x = clouds(2, n=4096, seed=5)
    with torch.no_grad():
        y = model(x)
    enc = Encoder(model, cfg)
    e = enc.embed(x.numpy())
    assert e.shape == (2, 256) and e.dtype == np.float32
    assert np.abs(e - y.numpy()).max() < 1e-5
    perm = torch.randperm(4096)
    assert np.abs(enc.embed(x[:, perm]) - e).max() < 1e-5


# -- folded inference -------------------------------------------------------------------------


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


def test_encoder_cloud_workers_agree_and_leave_thread_count() -> None:
    """Clouds run side by side on worker threads give the model's descriptors, in batch order,
    and the workers' single intra-op thread does not leak into the calling thread."""
    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    x = clouds(7, seed=4)
    with torch.no_grad():
        want = model(x).numpy()
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


# -- checkpoints ------------------------------------------------------------------------------


def test_save_load_round_trip(tmp_path: Path) -> None:
    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    d = save_model(tmp_path / "m", model, cfg, meta={"note": "test", "format": "spoofed"})
    assert sorted(p.name for p in d.iterdir()) == ["model.json", "model.safetensors"]
    doc = json.loads((d / "model.json").read_text())
    assert doc["format"] == "pnvlad-model" and doc["version"] == 1 and doc["note"] == "test"
    assert ModelConfig.model_validate(doc["model"]) == cfg
    assert doc["config_sha256"] == config_sha256(cfg)
    sha = hashlib.sha256((d / "model.safetensors").read_bytes()).hexdigest()
    assert weights_sha256(d) == sha == doc["weights_sha256"]

    loaded, cfg2 = load_model(d)
    assert cfg2 == cfg and not loaded.training
    x = clouds(2)
    with torch.no_grad():
        assert torch.equal(loaded(x), model(x))
    enc = Encoder.from_checkpoint(d)
    assert enc.weights_sha256 == sha == Encoder(model, cfg).weights_sha256
    with pytest.raises(FileExistsError):
        save_model(d, model, cfg)
    save_model(d, build_model(cfg), cfg, overwrite=True)
    assert weights_sha256(d) != sha
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no leftovers


def test_load_refuses_damaged_or_mismatched_dirs(tmp_path: Path) -> None:
    cfg = CONFIGS["compact"]
    d = save_model(tmp_path / "m", trained_like(cfg), cfg)
    with pytest.raises(InputError, match="model directory"):
        load_model(tmp_path / "nope")

    # Flip one byte of the weights: the recorded SHA-256 no longer matches.
    w = d / "model.safetensors"
    data = bytearray(w.read_bytes())
    data[-1] ^= 0xFF
    w.write_bytes(bytes(data))
    with pytest.raises(InputError, match="SHA-256"):
        load_model(d)

    # A config that does not fit the weights: the error lists what is missing and mis-shaped.
    d2 = save_model(tmp_path / "m2", trained_like(cfg), cfg)
    doc = json.loads((d2 / "model.json").read_text())
    doc["model"]["cluster_size"] = 8
    doc["model"]["feature_transform"] = True
    (d2 / "model.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        load_model(d2)
    msg = str(err.value)
    assert "missing" in msg and "feature_tnet.out.weight" in msg
    assert "shape mismatch" in msg and "pool.cluster_weights" in msg

    doc["format"] = "other"
    (d2 / "model.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="format"):
        load_model(d2)


@pytest.mark.real_scans
def test_real_scan_descriptor_is_order_independent(real_scans: Path) -> None:
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


@pytest.mark.slow
def test_compact_config_learns_to_tell_places_apart() -> None:
    """60 Adam steps of the lazy quadruplet loss on 12 synthetic 'places' (the same four blobs,
    each place moving them a little; a new point sample and offset every time) lift top-1
    retrieval of fresh samples well above the untrained network's."""
    from pnvlad_service.training.losses import lazy_quadruplet_loss

    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    places, n = 12, 256
    common = torch.rand(4, 3, generator=g) * 1.6 - 0.8
    spread = torch.rand(4, 3, generator=g) * 0.3 + 0.1
    centres = [common + (torch.rand(4, 3, generator=g) - 0.5) * 0.25 for _ in range(places)]

    def sample(s: int, gen: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, 4, (n,), generator=gen)
        pts = centres[s][idx] + torch.randn(n, 3, generator=gen) * spread[idx]
        return (pts + 0.03 * torch.randn(1, 3, generator=gen)).clamp(-1, 1)

    cfg = ModelConfig.compact(num_points=n)
    model = build_model(cfg)

    def recall_at_1() -> float:
        ge = torch.Generator().manual_seed(123)
        db = torch.stack([sample(s, ge) for s in range(places)])
        q = torch.stack([sample(s, ge) for s in range(places)])
        enc = Encoder(model, cfg)
        d, e = enc.embed(db), enc.embed(q)
        nearest = ((e[:, None] - d[None]) ** 2).sum(-1).argmin(1)
        return float((nearest == np.arange(places)).mean())

    before = recall_at_1()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    for _ in range(60):
        tuples = []
        for s in torch.randint(0, places, (2,), generator=g).tolist():
            others = [o for o in range(places) if o != s]
            order = torch.randperm(len(others), generator=g).tolist()
            negs = [others[i] for i in order[:7]]
            tuples += [sample(s, g) for _ in range(3)] + [sample(m, g) for m in negs]
            tuples.append(sample(others[order[7]], g))
        d = model(torch.stack(tuples)).reshape(2, 11, -1)
        loss = lazy_quadruplet_loss(d[:, 0], d[:, 1:3], d[:, 3:10], d[:, 10])
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = recall_at_1()
    assert after >= 0.5 and after >= before + 0.25, (before, after)
