"""Training: config, schedules, one forward per cloud a step, resume after SIGKILL, torchrun."""

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
import yaml

from pnvlad_service.errors import InputError
from pnvlad_service.training.config import TrainConfig

REPO = Path(__file__).resolve().parents[1]
BASE_N, BASE_E = 5_000_000.0, 600_000.0


# ---------------------------------------------------------------------------------------------
# A tiny benchmark tree: 3 runs along a 300 m street of box-shaped landmarks


def _landmarks(seed: int = 7) -> np.ndarray:
    """float64 [L, 6]: northing, easting (local metres), half sizes (n, e), height, kind."""
    rng = np.random.default_rng(seed)
    n = rng.uniform(-30, 330, 120)
    e = rng.choice([-1, 1], 120) * rng.uniform(6, 25, 120)
    return np.stack(
        [
            n,
            e,
            rng.uniform(0.5, 4, 120),
            rng.uniform(0.5, 4, 120),
            rng.uniform(1, 12, 120),
            rng.integers(0, 3, 120),
        ],
        axis=1,
    )


def _cloud(lm: np.ndarray, north: float, east: float, rng: np.random.Generator) -> np.ndarray:
    """float64 [4096, 3] in [-1, 1]: points on the landmarks within 25 m, centred and scaled."""
    near = lm[np.hypot(lm[:, 0] - north, lm[:, 1] - east) < 25.0]
    near = near[rng.random(len(near)) > 0.1]  # a run misses a few landmarks (parked cars...)
    if len(near) == 0:
        near = lm[np.argsort(np.hypot(lm[:, 0] - north, lm[:, 1] - east))[:2]]
    pick = near[rng.integers(0, len(near), 4096)]
    u = rng.uniform(-1, 1, (4096, 3))
    pts = np.stack(
        [
            pick[:, 1] + u[:, 1] * pick[:, 3] - east,
            pick[:, 0] + u[:, 0] * pick[:, 2] - north,
            (u[:, 2] + 1) / 2 * pick[:, 4],
        ],
        axis=1,
    )
    pts += rng.normal(scale=0.05, size=pts.shape)
    pts -= pts.mean(0)
    pts /= max(np.abs(pts).max(), 1e-6)
    return pts


def make_tiny_tree(root: Path, runs: int = 3, train_step: float = 4.0) -> Path:
    """A benchmark tree ``root/city/run<k>`` (oxford layout) with a test region around 220 m
    (half size 50 m) and ``root/splits.json``. Returns the splits path."""
    from pnvlad_service.data import splits
    from pnvlad_service.data import tree as benchmark

    lm = _landmarks()
    for r in range(runs):
        rng = np.random.default_rng(100 + r)
        run = root / "city" / f"2020-01-0{r + 1}-00-00-00"
        for kind, folder, csv, step in (
            (
                "train",
                "pointcloud_20m_10overlap",
                "pointcloud_locations_20m_10overlap.csv",
                train_step,
            ),
            ("test", "pointcloud_20m", "pointcloud_locations_20m.csv", 10.0),
        ):
            (run / folder).mkdir(parents=True, exist_ok=True)
            rows = []
            for k, n in enumerate(np.arange(0.0, 300.0, step)):
                east = rng.normal(scale=1.0)
                ts = 1_600_000_000_000_000 + r * 10**10 + k * 10**6 + (kind == "test")
                _cloud(lm, n, east, rng).astype("<f8").tofile(run / folder / f"{ts}.bin")
                rows.append((ts, BASE_N + n, BASE_E + east))
            benchmark.write_locations_csv(run / csv, rows)
    regions = splits.TestRegions(((BASE_N + 220.0, BASE_E),), 50.0)
    splits.save_regions(root / "city" / splits.REGIONS_FILE, regions)
    s = splits.build_splits(root)
    splits.save_splits(root / "splits.json", s)
    return root / "splits.json"


@pytest.fixture(scope="session")
def tiny_tree(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("tiny_tree")
    return root, make_tiny_tree(root)


def tiny_config(root: Path, splits: Path, **train: object) -> TrainConfig:
    """A very small network and run: 128 points, K = 4, 32-d output, 1 thread."""
    cfg = TrainConfig.from_mapping(
        {
            "model": {
                "preset": "compact",
                "num_points": 128,
                "cluster_size": 4,
                "output_dim": 32,
                "stem_widths": [16],
                "trunk_widths": [32, 64],
                "tnet_point_widths": [16, 32],
                "tnet_fc_widths": [16],
            },
            "train": {
                "batch_size": 2,
                "positives": 2,
                "negatives": 6,
                "hard_negatives": 3,
                "sampled_negatives": 40,
                "cache_warmup_epochs": 0,
                "cache_refresh_steps": 3,
                "checkpoint_every": 2,
                "log_every": 1,
                "val_every": 0,
                "threads": 1,
                "workers": 2,
                "lr": 1e-3,
                **train,
            },
            "data": {"root": str(root), "splits": str(splits)},
        }
    )
    return cfg


# ---------------------------------------------------------------------------------------------
# config and schedules


def test_config_file_partial_fields_and_overrides(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("model: {preset: compact, num_points: 512}\ntrain: {lr: 0.001, epochs: 3}\n")
    cfg = TrainConfig.from_file(p)
    assert cfg.model.num_points == 512 and cfg.model.cluster_size == 16
    assert cfg.train.lr == 1e-3 and cfg.train.epochs == 3 and cfg.train.negatives == 18
    cfg2 = cfg.with_overrides({"train.batch_size": 8, "model.arch": "pointnet-max", "x": None})
    assert cfg2.train.batch_size == 8 and cfg2.model.arch == "pointnet-max"
    # the dumped YAML holds every field and reads back to the same config
    assert TrainConfig.from_mapping(yaml.safe_load(cfg2.to_yaml())) == cfg2
    t = tmp_path / "c.toml"
    t.write_text("[train]\nseed = 5\n")
    assert TrainConfig.from_file(t).train.seed == 5


def test_config_errors_name_the_field(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("train: {lr: -1}\n")
    with pytest.raises(InputError, match=r"train\.lr"):
        TrainConfig.from_file(p)
    p.write_text("train: {learning_rate: 1}\n")
    with pytest.raises(InputError, match="learning_rate"):
        TrainConfig.from_file(p)
    with pytest.raises(InputError, match="unknown config field"):
        TrainConfig().with_overrides({"nope.x": 1})
    with pytest.raises(InputError):
        TrainConfig.from_file(tmp_path / "missing.yaml")


def test_shipped_configs_load() -> None:
    paper = TrainConfig.preset("paper")
    assert paper == TrainConfig()  # paper.yaml lists exactly the defaults
    assert paper.train.lr == 5e-5 and paper.train.negatives == 18 and paper.train.positives == 2
    assert paper.model.cluster_size == 64
    assert TrainConfig.preset("compact").model.cluster_size == 16


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


# ---------------------------------------------------------------------------------------------
# training in-process


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


# ---------------------------------------------------------------------------------------------
# real processes: kill and resume, torchrun


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
    cfg_path.write_text(tiny_config(root, splits).to_yaml())
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
