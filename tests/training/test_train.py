"""Training: schedules, one forward per cloud a step, resume after SIGKILL, torchrun."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.training.config import TrainConfig
from tests.training.street import tiny_config


def test_schedules_hand_worked() -> None:
    from pnvlad_service.training.train import bn_momentum, learning_rate

    cfg = TrainConfig()  # batch 2, decay every 200,000 tuples
    assert learning_rate(cfg, 0) == pytest.approx(5e-5)
    assert learning_rate(cfg, 99_999) == pytest.approx(5e-5)
    assert learning_rate(cfg, 100_000) == pytest.approx(5e-5 * 0.7)
    assert learning_rate(cfg, 10**7) == pytest.approx(1e-5)  # floored
    assert bn_momentum(cfg, 0) == pytest.approx(0.5)  # TF decay 0.5
    assert bn_momentum(cfg, 100_000) == pytest.approx(0.25)
    assert bn_momentum(cfg, 10**7) == pytest.approx(0.01)  # decay clipped at 0.99


def test_warmup_and_cosine_schedule_hand_worked() -> None:
    from pnvlad_service.training.train import learning_rate

    cfg = TrainConfig.from_mapping(
        {"train": {"lr": 1e-3, "lr_min": 1e-5, "lr_schedule": "cosine", "warmup_steps": 10}}
    )
    assert learning_rate(cfg, 0, 110) == pytest.approx(1e-4)  # 1/10 of the way up
    assert learning_rate(cfg, 9, 110) == pytest.approx(1e-3)
    assert learning_rate(cfg, 10, 110) == pytest.approx(1e-3)  # the cosine starts at lr
    # half way through the 100 cosine steps: the mean of lr and lr_min
    assert learning_rate(cfg, 60, 110) == pytest.approx((1e-3 + 1e-5) / 2)
    assert learning_rate(cfg, 35, 110) == pytest.approx(1e-5 + (1e-3 - 1e-5) * 0.5 * (1 + 2**-0.5))
    assert learning_rate(cfg, 110, 110) == pytest.approx(1e-5)
    assert learning_rate(cfg, 500, 110) == pytest.approx(1e-5)  # past the end: the floor
    with pytest.raises(ValueError, match="total steps"):
        learning_rate(cfg, 20)
    # warm-up before the paper's staircase
    stair = TrainConfig.from_mapping({"train": {"warmup_steps": 4}})
    assert learning_rate(stair, 1) == pytest.approx(5e-5 / 2)
    assert learning_rate(stair, 4) == pytest.approx(5e-5)


def test_each_cloud_embedded_once_per_step(tiny_tree: tuple[Path, Path], tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from pnvlad_service.training.train import train

    root, splits = tiny_tree
    cfg = tiny_config(root, splits, max_steps=3, cache_refresh_steps=100)
    calls: list[tuple[bool, int]] = []
    steps: list[dict] = []

    def on_model(model: torch.nn.Module) -> None:
        model.register_forward_hook(lambda m, inp, out: calls.append((m.training, inp[0].shape[0])))

    threads = torch.get_num_threads()
    try:
        res = train(cfg, tmp_path / "run", progress=False, on_model=on_model, on_step=steps.append)
    finally:
        torch.set_num_threads(threads)
    assert res.steps == 3 and len(res.losses) == 3
    train_calls = [n for training, n in calls if training]
    # one forward pass a step, over exactly the distinct clouds of the step's tuples
    assert len(train_calls) == 3
    for n, rec in zip(train_calls, steps, strict=True):
        table = np.asarray(rec["indices"])
        assert table.shape == (2, 1 + 2 + 6 + 1)
        assert n == len(set(table.ravel().tolist())) == rec["clouds"]
    # the cache (eval mode) embedded the training set once
    from pnvlad_service.data.dataset import load_training_data

    ts, _ = load_training_data(cfg.data)
    assert sum(n for training, n in calls if not training) == len(ts)
    assert res.cache_refreshes == 1
    # outputs: final model loadable, metrics log with steps and the cache event
    from pnvlad_service.models.store import load_model

    _, mcfg = load_model(tmp_path / "run" / "model")
    assert mcfg == cfg.model
    events = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    kinds = [e["event"] for e in events]
    assert kinds[0] == "start" and kinds[-1] == "end" and "cache" in kinds
    assert [e["step"] for e in events if e["event"] == "step"] == [1, 2, 3]
    for e in events:
        if e["event"] == "step":
            assert np.isfinite(e["loss"]) and e["lr"] == 1e-3 and e["steps_per_s"] > 0


def test_in_batch_mining_reuses_embeddings(tiny_tree: tuple[Path, Path], tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from pnvlad_service.training.train import train

    root, splits = tiny_tree
    cfg = tiny_config(root, splits, max_steps=2, mining="in_batch", batch_size=6, val_every=2)
    rows: list[int] = []
    steps: list[dict] = []

    def on_model(model: torch.nn.Module) -> None:
        model.register_forward_hook(
            lambda m, inp, out: rows.append(inp[0].shape[0]) if m.training else None
        )

    threads = torch.get_num_threads()
    try:
        res = train(cfg, tmp_path / "run", progress=False, on_model=on_model, on_step=steps.append)
    finally:
        torch.set_num_threads(threads)
    assert res.cache_refreshes == 0
    for n, rec in zip(rows, steps, strict=True):
        members = np.asarray(rec["indices"])
        assert n == len(members) == len(set(members.tolist())) <= 12
    assert all(np.isfinite(v) for v in res.losses.values())
    assert res.last_val is not None and 0 <= res.last_val["recall_at_1"] <= 100


def test_resampling_draws_a_fresh_subset_of_the_whole_submap_each_step(
    tiny_tree: tuple[Path, Path], tmp_path: Path
) -> None:
    torch = pytest.importorskip("torch")
    from pnvlad_service.data.dataset import load_training_data, read_submap
    from pnvlad_service.training.train import train

    root, splits = tiny_tree
    cfg = tiny_config(
        root, splits, max_steps=4, mining="in_batch", batch_size=6, resample_points=True
    )
    seen: list[np.ndarray] = []
    steps: list[dict] = []

    def on_model(model: torch.nn.Module) -> None:
        def keep(m: torch.nn.Module, inp: tuple) -> None:
            if m.training:
                seen.append(inp[0].detach().numpy().copy())

        model.register_forward_pre_hook(keep)

    threads = torch.get_num_threads()
    try:
        res = train(cfg, tmp_path / "run", progress=False, on_model=on_model, on_step=steps.append)
    finally:
        torch.set_num_threads(threads)
    assert res.losses
    paths = load_training_data(cfg.data)[0].paths
    subsets: dict[int, list[frozenset]] = {}
    for x, rec in zip(seen, steps, strict=True):
        assert x.shape[1:] == (128, 3)
        for cloud, i in zip(x, rec["indices"], strict=True):
            whole = {tuple(r) for r in read_submap(paths[i]).tolist()}
            rows = [tuple(r) for r in cloud.tolist()]
            assert all(r in whole for r in rows)  # points of the whole submap...
            assert len(set(rows)) == 128  # ...drawn without repeats
            subsets.setdefault(int(i), []).append(frozenset(rows))
    again = [v for v in subsets.values() if len(v) > 1]
    assert again, "no cloud was embedded twice in four steps"
    assert all(len(set(v)) == len(v) for v in again)  # a fresh subset every time


def test_refuses_to_overwrite_a_run(tiny_tree: tuple[Path, Path], tmp_path: Path) -> None:
    pytest.importorskip("torch")
    from pnvlad_service.training.train import train

    root, splits = tiny_tree
    cfg = tiny_config(root, splits, max_steps=1)
    train(cfg, tmp_path / "run", progress=False)
    with pytest.raises(InputError, match="already holds"):
        train(cfg, tmp_path / "run", progress=False)
    with pytest.raises(InputError, match="no checkpoint"):
        train(cfg, tmp_path / "other", progress=False, resume=True)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "pnvlad_cli.main", "-q", "train", "--no-progress", *args]


def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def _step_losses(metrics: Path, after_resume: bool = False) -> dict[int, float]:
    out: dict[int, float] = {}
    seen = not after_resume
    for line in metrics.read_text().splitlines():
        e = json.loads(line)
        if e["event"] == "start" and e["resumed"]:
            seen = True
        if e["event"] == "step" and seen:
            out[e["step"]] = e["loss"]
    return out


@pytest.mark.slow
def test_resume_after_sigkill_continues_exactly(
    tiny_tree: tuple[Path, Path], tmp_path: Path
) -> None:
    pytest.importorskip("torch")
    from safetensors.numpy import load_file

    root, splits = tiny_tree
    cfg_path = tmp_path / "tiny.yaml"
    # With augmentation and the cosine schedule: both must repeat after a resume.
    aug = {"yaw_deg": 10.0, "jitter": 0.01, "dropout": 0.2, "erase_p": 0.5, "shift": 0.02}
    cfg = tiny_config(
        root, splits, augment=aug, lr_schedule="cosine", warmup_steps=2, resample_points=True
    )  # the resampled subsets, too
    cfg_path.write_text(cfg.to_yaml())
    # reference: an uninterrupted run of 9 steps (in this process: one torch start-up less)
    import torch

    from pnvlad_service.training.train import train

    ref = tmp_path / "ref"
    threads = torch.get_num_threads()
    try:
        train(
            TrainConfig.from_file(cfg_path).with_overrides({"train.max_steps": 9}),
            ref,
            progress=False,
        )
    finally:
        torch.set_num_threads(threads)
    # the same run, killed with SIGKILL once a checkpoint exists
    run = tmp_path / "run"
    proc = subprocess.Popen(
        _cli("-c", str(cfg_path), "-o", str(run), "--max-steps", "1000"), env=_env()
    )
    latest = run / "checkpoints" / "latest"
    deadline = time.monotonic() + 120
    while not latest.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    killed_at = int(latest.read_text().strip().split("-")[1])
    assert killed_at < 9
    # resume to 9 steps: same losses step for step, same final weights
    subprocess.run(
        _cli("-o", str(run), "--resume", "--max-steps", "9"), check=True, env=_env(), timeout=120
    )
    ref_losses = _step_losses(ref / "metrics.jsonl")
    resumed = _step_losses(run / "metrics.jsonl", after_resume=True)
    assert sorted(resumed) == list(range(killed_at + 1, 10))
    for step, loss in resumed.items():
        assert loss == ref_losses[step], f"step {step}"
    a = load_file(ref / "model" / "model.safetensors")
    b = load_file(run / "model" / "model.safetensors")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
def test_torchrun_two_processes_gloo(tiny_tree: tuple[Path, Path], tmp_path: Path) -> None:
    pytest.importorskip("torch")
    root, splits = tiny_tree
    cfg_path = tmp_path / "tiny.yaml"
    cfg_path.write_text(tiny_config(root, splits, checkpoint_every=1000).to_yaml())
    out = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "pnvlad_cli.main",
        "-q",
        "train",
        "--no-progress",
        "-c",
        str(cfg_path),
        "-o",
        str(out),
        "--max-steps",
        "4",
        "--max-minutes",  # exercises the ranks' agreement on the budget every step
        "30",
        "--device",
        "cpu",
    ]
    subprocess.run(cmd, check=True, env=_env(), timeout=180)
    ckpts = sorted(p.name for p in (out / "checkpoints").iterdir() if p.name.startswith("step-"))
    assert ckpts == ["step-00000004"]
    assert (out / "model" / "model.safetensors").is_file()
    events = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert events[0]["world"] == 2
    steps = [e["step"] for e in events if e["event"] == "step"]
    assert steps == [1, 2, 3, 4]  # written by rank 0 only: no duplicates
    assert sum(e["event"] == "cache" for e in events) == 2  # at steps 0 and 3


def test_published_pickles_train_like_our_splits(
    tiny_tree: tuple[Path, Path], tmp_path: Path
) -> None:
    """Tuples read from exported published-format pickles give the very same run."""
    torch = pytest.importorskip("torch")
    from pnvlad_service.data import splits as sp
    from pnvlad_service.training.train import train

    root, splits = tiny_tree
    sp.export_pickles(sp.load_splits(splits), tmp_path / "pk")
    cfg = tiny_config(root, splits, max_steps=3)
    cfg_pk = TrainConfig.from_mapping(
        {**cfg.model_dump(), "data": {"root": str(root), "pickles": str(tmp_path / "pk")}}
    )
    threads = torch.get_num_threads()
    try:
        a = train(cfg, tmp_path / "a", progress=False)
        b = train(cfg_pk, tmp_path / "b", progress=False)
    finally:
        torch.set_num_threads(threads)
    assert a.losses == b.losses


# ---------------------------------------------------------------------------------------------
# data too small for the configured tuple: adapt, or one clear error before anything is written


@pytest.fixture(scope="module")
def synth_tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`pnvlad synth --preset tiny` (its default seed): 33 training submaps, every anchor with
    15 to 18 negatives, fewer than the paper's 18 negatives and 1 other negative a tuple."""
    from pnvlad_service.synth.generate import generate

    root = tmp_path_factory.mktemp("synth") / "t"
    generate("tiny", root, seed=0, workers=2, progress=False)
    return root


@pytest.mark.parametrize(
    "config", [[], ["-c", "compact"], ["-c", "bev"]], ids=["paper", "compact", "bev"]
)
def test_the_tiny_synth_preset_trains_with_the_default_command(
    synth_tiny: Path, tmp_path: Path, config: list[str]
) -> None:
    """`pnvlad train --root t --out r` on the tiny preset (it died with a ValueError traceback
    from mining): the tuple shrinks to the negatives the set holds, and a warning names the
    option (bev: the bev-netvlad model, trained with in-batch mining). --num-points only keeps
    the step quick; the tuple is the configured one."""
    pytest.importorskip("torch")
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.data.dataset import load_training_data

    cfg = TrainConfig.preset(config[-1] if config else "paper")
    ts, _ = load_training_data(cfg.with_overrides({"data.root": synth_tiny}).data)
    anchors = ts.anchors()
    every = np.arange(len(ts))
    fewest = min(int(ts.negative_mask(int(a), every[every != a]).sum()) for a in anchors)
    assert fewest <= cfg.train.negatives  # the preset is too small for the configured tuple
    run = tmp_path / "r"
    args = ["-q", "train", *config, "--root", str(synth_tiny), "--out", str(run)]
    res = CliRunner().invoke(app, [*args, "--max-steps", "1", "--num-points", "256"])
    assert res.exit_code == 0, res.output
    assert "Traceback" not in res.output
    if cfg.train.mining != "in_batch":  # in-batch mining takes the batch's negatives
        assert f"using {fewest - 1} negatives a tuple" in res.output
        assert "train.negatives" in res.output
    assert "1 steps (max_steps)" in res.stdout
    steps = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    step = [e for e in steps if e["event"] == "step"]
    assert len(step) == 1 and np.isfinite(step[0]["loss"])
    from pnvlad_service.models.store import load_model

    _, mcfg = load_model(run / "model")
    assert mcfg.cluster_size == cfg.model.cluster_size  # the preset's model, not a stand-in
    assert mcfg.arch == cfg.model.arch


def test_too_few_anchors_for_the_batch_is_one_line_and_writes_nothing(
    synth_tiny: Path, tmp_path: Path
) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    run = tmp_path / "r"
    res = CliRunner().invoke(
        app, ["-q", "train", "-r", str(synth_tiny), "-o", str(run), "--batch-size", "64"]
    )
    assert res.exit_code == 2
    assert res.output.count("\n") == 1 and "fewer than the batch size 64" in res.output
    assert "--batch-size" in res.output
    assert not run.exists()


def test_a_set_without_room_for_a_tuple_is_refused_before_writing(tmp_path: Path) -> None:
    """Submaps along 40 m only: no anchor has 2 negatives (one for the tuple, one "other"):
    an InputError naming train.mining, and the output directory never appears."""
    pytest.importorskip("torch")
    from pnvlad_service.data.dataset import TrainingSet
    from pnvlad_service.training.train import train

    north = np.arange(9) * 5.0
    positives = [np.flatnonzero((np.abs(north - n) <= 10) & (north != n)) for n in north]
    ts = TrainingSet([tmp_path / f"{i}.bin" for i in range(9)], np.c_[north, 0 * north], positives)
    cfg = TrainConfig().with_overrides({"train.device": "cpu"})
    with pytest.raises(InputError, match="too small for tuple mining") as err:
        train(cfg, tmp_path / "run", training_set=ts, progress=False)
    assert err.value.source == "train.mining"
    assert not (tmp_path / "run").exists()
