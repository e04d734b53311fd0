"""How big are the submaps? Their metric extent before the filter G, synthetic against real.

Usage: python benchmarks/submap_extent.py [--tree DIR ...] [--samples 40] [--box 25 30 40]
       [--real DIR] [--kitti-box 25 30 40] [--seed 0]

Per cloud, before G (metres): the sides of the smallest horizontal rectangle that holds it (its
long and short side, the rectangle turned in 1 degree steps, so a cloud turned about the
vertical, as the real Oxford clouds are, measures as it would unturned) and the height
(max - min of z); the same three between the 5th and 95th percentile of the points along those
axes (robust to a stray far return); and max - min along the cloud's own x and y (a submap's
are the map's east and north; the real Oxford clouds were turned at random). After G (the
normalised submap, mean distance 0.5): the height, max - min and p5-p95, and G's scale (metres
a normalised unit: twice the mean distance of G's points from their centroid, so what sets how
large a 10 m facade is drawn) and G's output taken back to metres by it (long and short side,
max - min and p5-p95: the ground removed and the cloud cropped to 2 scales across). A row
summarises its clouds by the median and, in brackets, the 5th to 95th percentile over them.

Sources:

- ``--tree DIR``: a ``pnvlad synth`` tree. ``--samples`` of its test-layout submaps (seeded,
  across its runs) are laid again before G exactly as prepare laid them
  (``data.prepare.laid_window`` with the options of the run's prepare record, the box
  included): each run's drive is cast again from synth.json, only the scans the samples need.
  After G: the tree's own ``.bin``. ``--box B``: the same windows also cut to a B m square
  (UTM-aligned, centred on the submap's location) and put through the tree's G (its prepare
  record's settings and seed), one row per box.
- ``--real DIR`` (default $PNVLAD_REAL_SCANS or ../shared/data/real_scans): the two Oxford
  RobotCar push-broom clouds (``oxford_lms_front_*.bin``, float32 x 6, ground included) as
  they are, and KITTI 00 frames 94 and 95 laid together with their recorded poses (in frame
  94's velodyne frame), whole and cut to each ``--kitti-box`` square about frame 94. Their G is
  the default (the paper's).

Prints a Markdown table (docs/SYNTH.md's submap-size section); progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from entry import run

from pnvlad_service.errors import InputError

REPO = Path(__file__).resolve().parents[1]

#: KITTI sequence 00's velodyne -> camera 0 transform (``Tr`` of its calib.txt, as the real
#: scans' README gives it).
KITTI_TR = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
OXFORD_FILES = ("oxford_lms_front_270.bin", "oxford_lms_front_456.bin")
KITTI_FRAMES = (94, 95)


@dataclass(frozen=True)
class Extent:
    """One cloud's size: ``long``, ``short`` (sides of the smallest horizontal rectangle),
    ``height`` (max - min z), metres or normalised units; ``robust``: the same three between
    the 5th and 95th percentiles of the points along the rectangle's axes and z; ``xy``: max -
    min along the cloud's own x and y (the map's axes for a submap)."""

    long: float
    short: float
    height: float
    robust: tuple[float, float, float]
    xy: tuple[float, float] = (math.nan, math.nan)


def extent(points: np.ndarray, step_deg: float = 1.0, sample: int = 50_000) -> Extent:
    """The :class:`Extent` of ``points`` [N, 3+] (N >= 1). The rectangle's turn is searched
    over [0, 90) degrees in ``step_deg`` steps on at most ``sample`` points (evenly strided),
    its sides then measured on all of them."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    if pts.ndim != 2 or len(pts) == 0 or not np.isfinite(pts).all():
        raise InputError("an extent needs a finite non-empty [N, 3] cloud", "points")
    xy = pts[:, :2] - pts[:, :2].mean(axis=0)
    few = xy[:: max(1, len(xy) // sample)]
    angles = np.radians(np.arange(0.0, 90.0, step_deg))
    best, best_area = 0.0, math.inf
    for a in angles:
        u = few @ np.array([math.cos(a), math.sin(a)])
        v = few @ np.array([-math.sin(a), math.cos(a)])
        area = float(np.ptp(u) * np.ptp(v))
        if area < best_area:
            best, best_area = float(a), area
    u = xy @ np.array([math.cos(best), math.sin(best)])
    v = xy @ np.array([-math.sin(best), math.cos(best)])
    z = pts[:, 2]

    def spread(x: np.ndarray) -> float:
        lo, hi = np.percentile(x, [5, 95])
        return float(hi - lo)

    sides = sorted([(float(np.ptp(u)), spread(u)), (float(np.ptp(v)), spread(v))], reverse=True)
    return Extent(
        sides[0][0],
        sides[1][0],
        float(np.ptp(z)),
        (sides[0][1], sides[1][1], spread(z)),
        (float(np.ptp(pts[:, 0])), float(np.ptp(pts[:, 1]))),
    )


@dataclass
class Row:
    """One source: its label and the extents of its clouds before and after G."""

    label: str
    before: list[Extent]
    after: list[Extent]
    points: list[int]
    scales: list[float] = field(default_factory=list)


def _stat(values: list[float], digits: int = 1) -> str:
    """``median [p5-p95]`` of ``values`` (one value: itself)."""
    v = np.asarray(values, dtype=np.float64)
    med = float(np.median(v))
    if len(v) == 1:
        return f"{med:.{digits}f}"
    lo, hi = np.percentile(v, [5, 95])
    return f"{med:.{digits}f} [{lo:.{digits}f}-{hi:.{digits}f}]"


def table(rows: list[Row]) -> str:
    """The Markdown table of ``rows``."""
    lines = [
        "| source | clouds | points before G | long side, m | short side, m | height, m "
        "| p5-p95: long / short / height, m | x / y, m | G's scale, m a unit "
        "| G's output in metres: long x short (p5-p95) | height after G: max-min / p5-p95 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rob = [float(np.median([e.robust[k] for e in r.before])) for k in range(3)]
        xy = [float(np.median([e.xy[k] for e in r.before])) for k in range(2)]
        # G's output back in metres (ground removed, cropped to [-1, 1], so at most 2 scales).
        out = [
            float(np.median([v * sc for v, sc in zip(vals, r.scales, strict=True)]))
            for vals in (
                [e.long for e in r.after],
                [e.short for e in r.after],
                [e.robust[0] for e in r.after],
                [e.robust[1] for e in r.after],
            )
        ]
        lines.append(
            f"| {r.label} | {len(r.before)} | {int(np.median(r.points)):,} "
            f"| {_stat([e.long for e in r.before])} | {_stat([e.short for e in r.before])} "
            f"| {_stat([e.height for e in r.before])} "
            f"| {rob[0]:.1f} / {rob[1]:.1f} / {rob[2]:.1f} | {xy[0]:.0f} / {xy[1]:.0f} "
            f"| {_stat(r.scales)} "
            f"| {out[0]:.0f} x {out[1]:.0f} ({out[2]:.0f} x {out[3]:.0f}) "
            f"| {_stat([e.height for e in r.after], 2)} / "
            f"{float(np.median([e.robust[2] for e in r.after])):.2f} |"
        )
    return "\n".join(lines)


def box_cut(points: np.ndarray, box_m: float) -> np.ndarray:
    """The points with |x| and |y| <= ``box_m`` / 2 (as ``data.accumulate.accumulate`` cuts)."""
    half = box_m / 2.0
    return points[(np.abs(points[:, 0]) <= half) & (np.abs(points[:, 1]) <= half)]


# --------------------------------------------------------------------------------------------
# A pnvlad synth tree: windows laid again as prepare laid them
# --------------------------------------------------------------------------------------------


def _record(run_dir: Path, folder: str) -> dict[str, Any]:
    path = run_dir / f".prepare-{folder}.json"
    if not path.is_file():
        raise InputError("no prepare record: is this a pnvlad synth tree?", path)
    return json.loads(path.read_text(encoding="utf-8"))


def _samples(root: Path, n: int, seed: int) -> list[tuple[str, str, int]]:
    """(area, run, timestamp) of ``n`` test-layout submaps of the tree, drawn without
    replacement (seeded), in tree order."""
    from pnvlad_service.data.tree import BenchmarkTree

    tree = BenchmarkTree(root)
    every = [
        (d, r, int(t))
        for d in tree.datasets
        for r in tree.runs(d)
        if tree.has(d, r, "test")
        for t in tree.locations(d, r, "test").timestamp
    ]
    if not every:
        raise InputError("no test-layout submaps", root)
    pick = np.random.default_rng(seed).choice(len(every), min(n, len(every)), replace=False)
    return [every[i] for i in sorted(pick)]


def tree_rows(root: Path, n: int, boxes: list[float], seed: int) -> list[Row]:
    """The tree's own submaps, then the same windows cut to each of ``boxes``."""
    from pnvlad_service.data.accumulate import ScanCache, travelled_distance, used_scans
    from pnvlad_service.data.cuts import submap_cuts
    from pnvlad_service.data.prepare import laid_window
    from pnvlad_service.data.tree import LAYOUTS
    from pnvlad_service.io.submap import read_submap
    from pnvlad_service.preprocess.filter_g import GConfig, apply_g
    from pnvlad_service.synth.generate import simulated_drive
    from pnvlad_service.synth.windows import drives_of

    drives = drives_of(root)
    folder = LAYOUTS["oxford"].folder("test")
    from pnvlad_service.data.frames import frames_path, read_frames_csv

    own = Row(f"{root.name}", [], [], [])
    boxed = {b: Row(f"{root.name}, cut to {b:g} m", [], [], []) for b in boxes}
    by_run: dict[tuple[str, str], list[int]] = {}
    for area, run_dir_name, stamp in _samples(root, n, seed):
        by_run.setdefault((area, run_dir_name), []).append(stamp)
    done = 0
    for (area, name), stamps in by_run.items():
        run_dir = root / area / name
        rec = _record(run_dir, folder)
        spec, a, k, s = drives[(area, name)]
        drive = simulated_drive(spec, a, k, s)
        poses = drive.poses
        travelled = travelled_distance(poses)
        use = used_scans(travelled, rec["min_scan_spacing_m"], rec["scan_step"])
        cuts = {
            int(drive.timestamps[c.scan]): c
            for c in submap_cuts(travelled, rec["window_m"], rec["stride_m"])
        }
        cache = ScanCache(
            drive,
            seed=rec["seed"],
            max_points_per_scan=rec["max_points_per_scan"],
            max_range_m=rec["max_range_m"],
        )
        g = GConfig.model_validate(rec["g_config"])
        csv = run_dir / LAYOUTS["oxford"].csv("test")
        scale = {f.timestamp: abs(f.scale) for f in read_frames_csv(frames_path(csv))}
        for stamp in stamps:
            cut = cuts[stamp]
            local = laid_window(cut, cache, poses, use, rec["box_m"])
            own.before.append(extent(local))
            own.points.append(len(local))
            own.after.append(extent(read_submap(run_dir / folder / f"{stamp}.bin")))
            own.scales.append(scale[stamp])
            for b, row in boxed.items():
                cut_pts = box_cut(local, b)
                row.before.append(extent(cut_pts))
                row.points.append(len(cut_pts))
                res = apply_g(cut_pts, g, seed=rec["seed"] + cut.scan)
                row.after.append(extent(res.points))
                row.scales.append(abs(res.scale))
            done += 1
            print(f"\r{root.name}: {done} submaps", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return [own, *boxed.values()]


# --------------------------------------------------------------------------------------------
# The real clouds
# --------------------------------------------------------------------------------------------


def oxford_row(real: Path) -> Row:
    """The two RobotCar push-broom clouds as they are (ground included), and after G."""
    from pnvlad_service.preprocess.filter_g import apply_g

    row = Row("Oxford RobotCar lms_front (real push-broom)", [], [], [])
    for name in OXFORD_FILES:
        pts = np.fromfile(real / name, dtype=np.float32).reshape(-1, 6)[:, :3].astype(np.float64)
        row.before.append(extent(pts))
        row.points.append(len(pts))
        res = apply_g(pts)
        row.after.append(extent(res.points))
        row.scales.append(abs(res.scale))
    return row


def kitti_cloud(real: Path, frames: tuple[int, ...] = KITTI_FRAMES) -> np.ndarray:
    """KITTI 00 ``frames`` laid together with their recorded poses, in the first frame's
    velodyne frame: float64 [N, 3] metres (the real scans' README: ``P_i = C_i Tr``)."""
    lines = (real / "kitti00_poses.txt").read_text().splitlines()

    def pose(i: int) -> np.ndarray:
        c = np.eye(4)
        c[:3, :4] = np.array(lines[i].split(), dtype=np.float64).reshape(3, 4)
        return c @ KITTI_TR

    ref = np.linalg.inv(pose(frames[0]))
    parts = []
    for i in frames:
        pts = np.fromfile(real / f"kitti00_{i:06d}.bin", dtype=np.float32).reshape(-1, 4)[:, :3]
        m = ref @ pose(i)
        parts.append(pts.astype(np.float64) @ m[:3, :3].T + m[:3, 3])
    return np.concatenate(parts)


def kitti_rows(real: Path, boxes: list[float]) -> list[Row]:
    from pnvlad_service.preprocess.filter_g import apply_g

    cloud = kitti_cloud(real)
    label = "KITTI 00 frames 94+95 (real HDL-64E)"
    rows = []
    for b in [None, *boxes]:
        pts = cloud if b is None else box_cut(cloud, b)
        name = label if b is None else f"{label}, cut to {b:g} m"
        res = apply_g(pts)
        rows.append(Row(name, [extent(pts)], [extent(res.points)], [len(pts)], [abs(res.scale)]))
    return rows


def _positive(text: str) -> float:
    v = float(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"a box must be a positive number of metres: {text}")
    return v


def _args() -> argparse.Namespace:
    default = os.environ.get("PNVLAD_REAL_SCANS") or str(REPO.parent / "shared/data/real_scans")
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--tree", type=Path, nargs="*", default=[], help="pnvlad synth trees")
    ap.add_argument("--samples", type=int, default=40, help="submaps measured a tree")
    ap.add_argument("--box", type=_positive, nargs="*", default=[], help="tree windows cut to")
    ap.add_argument("--real", type=Path, default=Path(default), help="the real scans' folder")
    ap.add_argument(
        "--kitti-box", type=_positive, nargs="*", default=[25.0, 30.0, 40.0], help="KITTI cut to"
    )
    ap.add_argument("--no-real", action="store_true", help="measure the trees only")
    ap.add_argument("--seed", type=int, default=0, help="seed of the submaps drawn")
    return ap.parse_args()


def main() -> int:
    args = _args()
    t0 = time.perf_counter()
    rows: list[Row] = []
    for root in args.tree:
        rows += tree_rows(root, args.samples, args.box, args.seed)
    if not args.no_real:
        if not (args.real / OXFORD_FILES[0]).is_file():
            raise InputError("the real scans are not there (--real, $PNVLAD_REAL_SCANS)", args.real)
        rows.append(oxford_row(args.real))
        rows += kitti_rows(args.real, args.kitti_box)
    if not rows:
        raise InputError("nothing to measure: give --tree or the real scans", "arguments")
    print(f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    print(table(rows))
    return 0


if __name__ == "__main__":
    run(main)
