"""Time the filter G on the real scans, per scan and per step, and report what it removes.

Usage: python benchmarks/bench_preprocess.py [--repeats 15] [--scans DIR]

For each scan: points in, after ground removal, the leaf size, then the median and minimum
wall time of each step and of the whole filter (``filter_g``), in milliseconds. With
``--ground`` it also prints the share of points within 0.2 m of the road surface (an estimate
independent of preprocess.py: per 2 m cell the 5th percentile of z, cells near a least-squares
plane through the cells 3-20 m away) in the raw scan and in G's output, for the 'local' and the
paper's 'plane' ground modes.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from entry import real_scans_default, run

from pnvlad_service.io.readers import read_points
from pnvlad_service.preprocess import filter_g as g
from pnvlad_service.preprocess import voxel
from pnvlad_service.preprocess.ground import fit_ground_plane, ground_surface, rotation_to_z

REPO = Path(__file__).resolve().parents[1]
SCANS = [
    ("kitti00_000000.bin", "kitti", 1.0),
    ("kitti00_000005.bin", "kitti", 1.0),
    ("nuscenes_lidar_top.bin", "nuscenes", 1.0),
    ("nclt_1326652795280148.bin", "nclt", -1.0),  # z points down
]


def _time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    fn()  # warm-up (imports, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, min(times) * 1e3


def _near_road_share(scan: np.ndarray, points: np.ndarray) -> float:
    """Share of ``points`` within 0.2 m of the road surface estimated from ``scan``."""
    sys.path.insert(0, str(REPO))
    from tests.preprocess.helpers import road_surface  # the G tests' estimate

    surface = road_surface(scan)
    return float(np.mean(np.abs(points[:, 2] - surface(points)) < 0.2))


def _bench_scan(
    path: Path, reader: str, up: float, cfg: g.GConfig, repeats: int, ground: bool
) -> None:
    raw = read_points(path, reader)
    pts = raw.astype(np.float64)
    res = g.apply_g(raw, cfg)
    rng = np.random.default_rng(0)
    normal, offset = fit_ground_plane(pts, rng=np.random.default_rng(0))
    rot = rotation_to_z(normal)
    xy = np.stack([pts @ rot[0], pts @ rot[1]], axis=1)
    height = pts @ normal + offset
    nonground = g.remove_ground(pts, cfg, rng=np.random.default_rng(0))
    leaf, _ = voxel.find_leaf_size(nonground, cfg.target_points)
    voxels = voxel.voxel_average(nonground, leaf) if len(nonground) > cfg.target_points else None
    steps: list[tuple[str, Callable[[], object]]] = [
        ("read", lambda: read_points(path, reader)),
        ("ground: RANSAC plane", lambda: fit_ground_plane(pts, rng=rng)),
        ("ground: height map", lambda: ground_surface(xy, height)),
        ("ground: whole step", lambda: g.ground_mask(pts, cfg, rng=rng)),
        ("voxel: leaf search", lambda: voxel.find_leaf_size(nonground, cfg.target_points)),
    ]
    if voxels is not None:
        steps.append(("voxel: average", lambda: voxel.voxel_average(nonground, leaf)))
    out = res.points
    steps += [
        ("normalise", lambda: g.normalize(out, cfg.target_points, rng=rng)),
        ("filter_g (total)", lambda: g.filter_g(raw, cfg)),
    ]
    print(
        f"{path.name}: {res.n_input:,} points, {res.n_nonground:,} after ground removal, "
        f"{res.n_voxels:,} voxels of {res.leaf_size:.3f} m, up {np.round(res.up, 3)}"
    )
    for label, fn in steps:
        med, best = _time(fn, repeats)
        print(f"{'':<28}{label:<22}{med:>10.1f}{best:>9.1f}")
    if ground:
        flip = np.array([1.0, up, up])
        scan = raw * flip
        line = f"{'':<28}near road (0.2 m): raw {_near_road_share(scan, scan):.1%}"
        for mode in ("local", "plane"):
            kept = g.apply_g(raw, cfg.model_copy(update={"ground_mode": mode, "normalize": False}))
            share = _near_road_share(scan, kept.points * flip)
            line += f", {mode} {share:.2%} ({kept.n_nonground:,} kept)"
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    default = real_scans_default()
    parser.add_argument("--scans", type=Path, default=Path(default))
    parser.add_argument("--ground", action="store_true", help="also report ground figures")
    args = parser.parse_args()
    cfg = g.GConfig()
    print(f"{'scan':<28}{'step':<22}{'median ms':>10}{'min ms':>9}")
    for name, reader, up in SCANS:
        path = args.scans / name
        if not path.is_file():
            print(f"{name}: missing, skipped")
            continue
        _bench_scan(path, reader, up, cfg, args.repeats, args.ground)


if __name__ == "__main__":
    run(main)
