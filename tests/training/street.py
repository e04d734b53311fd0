"""A tiny benchmark tree for the training and evaluation tests: 3 runs along a 300 m street of
box-shaped landmarks, and a very small network to train on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.training.config import TrainConfig

BASE_N, BASE_E = 5_000_000.0, 600_000.0


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
