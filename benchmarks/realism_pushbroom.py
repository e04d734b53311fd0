"""How real is the push-broom city? The statistics that tell push-broom clouds apart, of the
real Oxford RobotCar clouds, of synthetic push-broom clouds and of today's spinning-sensor
clouds, side by side.

Usage: python benchmarks/realism_pushbroom.py [--preset pushbroom_demo] [--spinning demo]
       [--seed 0] [--clouds 8] [--real DIR] [--ablation]

Real: ``oxford_lms_front_270.bin`` and ``_456.bin`` of ../shared/data/real_scans (or
$PNVLAD_REAL_SCANS, or --real), read in place: the RobotCar's front LMS-151 accumulated with
GPS/INS, a disc of 30 m radius, ground included, 16,384 points, a random yaw.
Synthetic: ``--clouds`` places along the runs of ``pnvlad synth --preset PRESET --seed SEED``
(cast again in memory; no tree is written), each laid as the real ones are
(:func:`pnvlad_service.synth.realism_cloud.lay_like_real`): the lines (or scans) recorded
within ``--reach`` metres of travel of the place, laid with the run's recorded poses, the disc
of 30 m about the place, 16,384 points at random, a random yaw; and the same places of the
``--spinning`` preset's runs (its scans, each its preset's ``max_points_per_scan`` subset).

Statistics (pnvlad_service/synth/realism_cloud.py): points before the downsampling; G's ground
share; heights above the ground plane; the metric extent; the spacing of the push-broom's lines
along the track and of the points within a line across it (a comb in the ground points' positions
along the track); the local shapes; after the filter G of a submap (ground removed, 4096 points,
normalised): the height extent and width in its units and the local shapes.

Then the submaps as ``pnvlad synth`` cuts them (the points recorded along 20 m of trajectory,
before G): their extent (max - min and 5th to 95th percentile along the UTM axes) and the
height extent after G, and the period of the comb in the ground points of the cloud before it
is laid (the real clouds went through a voxel grid of about 0.2 m, which hides their lines: the
comb found in them, and in every laid cloud, is the grid's) beside speed / rate, medians over
the places. ``--ablation``: the distances of a few statistics from the perfect scanner laid
with the true poses, through the real scanner's failures, to the recorded poses (the preset).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from entry import real_scans_default, run

from pnvlad_service.data.accumulate import accumulate, scan_subset, travelled_distance
from pnvlad_service.errors import InputError
from pnvlad_service.preprocess.filter_g import GConfig, apply_g
from pnvlad_service.preprocess.ground import fit_ground_plane
from pnvlad_service.synth import realism_cloud as rc

REAL = ("oxford_lms_front_270.bin", "oxford_lms_front_456.bin")


def real_stats(root: Path, args: argparse.Namespace) -> rc.CloudStats:
    """The pooled statistics of the real RobotCar clouds (float32 x 6: xyz, normal)."""
    stats = []
    for j, name in enumerate(REAL):
        path = root / name
        if not path.is_file():
            raise InputError("not there (--real or $PNVLAD_REAL_SCANS)", path)
        pts = np.fromfile(path, "<f4").reshape(-1, 6)[:, :3].astype(np.float64)
        stats.append(rc.cloud_stats(pts, sample=args.sample, seed=j))
    return rc.pool(stats)


def _places(drive: Any, count: int, reach: float) -> list[int]:
    """``count`` lines or scans of ``drive`` spread over its travel, ``reach`` from its ends."""
    d = travelled_distance(drive.poses)
    at = reach + (np.arange(count) + 0.5) / count * max(d[-1] - 2 * reach, 1.0)
    return [int(np.searchsorted(d, s)) for s in at]


def synthetic(preset: Any, args: argparse.Namespace) -> tuple[rc.CloudStats, dict[str, float], str]:
    """The pooled statistics of ``args.clouds`` clouds of a preset's runs (a name or a
    ``SynthPreset``) laid like the real ones, the medians of its submaps as cut, and its
    sensor's name."""
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    spec = get_preset(preset) if isinstance(preset, str) else preset
    preset = spec.name
    per_run = -(-args.clouds // spec.runs)
    stats, subs = [], []
    rng = np.random.default_rng(args.seed)
    sensor = ""
    for r in range(spec.runs):
        if len(stats) >= args.clouds:
            break
        drive = simulated_drive(spec, 0, r, args.seed)
        sensor = drive.lidar.name or sensor
        d = travelled_distance(drive.poses)
        limit = spec.max_points_per_scan  # what prepare keeps of a scan (a line: all)
        for c in _places(drive, per_run, args.reach)[: args.clouds - len(stats)]:
            near = np.flatnonzero(np.abs(d - d[c]) <= args.reach)
            scans = {
                i: scan_subset(np.asarray(drive.scan(i), np.float64), limit, (0, i)) for i in near
            }
            centre = drive.poses[c, :3, 3]
            cloud = accumulate(drive.poses, scans, near, centre)
            disc = int((np.hypot(cloud[:, 0], cloud[:, 1]) <= rc.REAL_RADIUS_M).sum())
            normal, offset = fit_ground_plane(cloud, rng=np.random.default_rng(c))
            ground = cloud[np.abs(cloud @ normal + offset) < rc.LINE_GROUND_M, :2]
            raw_lines = rc.scan_lines(ground)[0]  # before any voxel grid
            rate = getattr(drive.lidar, "rate_hz", None)
            laid = rc.lay_like_real(cloud, rng)
            stats.append(rc.cloud_stats(laid, raw_points=disc, sample=args.sample, seed=c))
            window = [i for i in near if abs(d[i] - d[c]) <= 10.0]
            sub = accumulate(drive.poses, scans, window, centre)
            g = apply_g(sub, GConfig(), seed=c).points
            p5, p95 = np.percentile(sub[:, :2], 5, axis=0), np.percentile(sub[:, :2], 95, axis=0)
            subs.append(
                [
                    *np.ptp(sub[:, :2], axis=0),
                    *(p95 - p5),
                    np.ptp(g[:, 2]),
                    raw_lines,
                    drive.speed / rate if rate else np.nan,
                ]
            )
            print(f"{preset} run {r} place {c}: {len(sub):,} submap points", file=sys.stderr)
    med = np.nanmedian(np.array(subs), axis=0) if np.isfinite(subs).any() else np.array(subs)[0]
    keys = ("span_x", "span_y", "p5_95_x", "p5_95_y", "g_height", "lines", "speed_rate")
    return rc.pool(stats), dict(zip(keys, med.tolist(), strict=True)), sensor


def _value(v: float, unit: str) -> str:
    if not np.isfinite(v):
        return "n/a"
    if unit == "":
        return f"{v:,.0f}"
    if unit == "m":
        return f"{v:.2f} m"
    if unit == "%":
        return f"{v:.1f} %"
    return f"{v:.2f}"


def _distance(v: float, unit: str) -> str:
    if not np.isfinite(v):
        return "n/a"
    return f"{v:+.0f} %" if unit == "%" else f"{v:+.1f} pp" if unit == "pp" else f"{v:.2f} {unit}"


def table(real: rc.CloudStats, synths: list[tuple[str, rc.CloudStats]]) -> str:
    """Markdown: a statistic a row; the real value, then each synthetic source and its
    distance."""
    head = ["statistic", f"real RobotCar LMS-151 ({real.clouds})"]
    for name, s in synths:
        head += [f"{name} ({s.clouds})", "distance"]
    rows = [rc.compare(real, s) for _, s in synths]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, first in enumerate(rows[0]):
        cells = [first.label, _value(first.real, first.unit)]
        for comparison in rows:
            r = comparison[i]
            cells += [_value(r.synth, r.unit), _distance(r.distance, r.distance_unit)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def submap_table(subs: list[tuple[str, dict[str, float]]]) -> str:
    head = "| submaps as cut (20 m of trajectory), medians | " + " | ".join(n for n, _ in subs)
    lines = [head + " |", "|---|" + "---|" * len(subs)]
    for key, label in (
        ("span_x", "extent east, max - min (m)"),
        ("span_y", "extent north, max - min (m)"),
        ("p5_95_x", "extent east, 5-95 % (m)"),
        ("p5_95_y", "extent north, 5-95 % (m)"),
        ("g_height", "height extent after G (its units)"),
        ("lines", "comb of the ground points before any voxel grid, period (m)"),
        ("speed_rate", "a line every speed / rate (m)"),
    ):
        cells = [_value(s[key], "g") for _, s in subs]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


#: The rows the ablation follows.
ABLATION_ROWS = (
    "ground (G's estimate)",
    "height above the ground (mean)",
    "share above 5 m",
    "extent, minor axis (5-95 %)",
    "planar shape",
    "scattered shape",
    "G: height extent (its units)",
    "G: planar shape",
    "G: scattered shape",
)


def ablation_steps(name: str) -> list[tuple[str, Any]]:
    """The push-broom preset ``name`` reached in steps of one change each: the perfect scanner
    laid with the true poses, then the real scanner's failures, then the recorded GNSS/INS
    poses (the preset)."""
    from pnvlad_service.synth.generate import get_preset

    spec = get_preset(name)
    perfect = {
        "dropout": 0.0,
        "dropout_far": 0.0,
        "dropout_grazing": 0.0,
        "glass_loss": 0.0,
        "dark_loss": 0.0,
        "foliage_depth": 0.0,
        "range_noise_per_100m": 0.0,
    }
    exact = spec.conditions.model_copy(update={"position_noise": 0.0, "heading_noise_deg": 0.0})
    failures = spec.model_copy(update={"conditions": exact})
    clean = failures.model_copy(update={"pushbroom": spec.pushbroom.model_copy(update=perfect)})
    return [("perfect, true poses", clean), ("failures", failures), ("recorded poses", spec)]


def ablation(real: rc.CloudStats, name: str, args: argparse.Namespace) -> str:
    """Each followed statistic's distance to the real clouds at every step (Markdown)."""
    steps = ablation_steps(name)
    cols: list[dict[str, str]] = []
    for _, spec in steps:
        stats, _, _ = synthetic(spec, args)
        cols.append(
            {r.label: _distance(r.distance, r.distance_unit) for r in rc.compare(real, stats)}
        )
    names = " → ".join(n for n, _ in steps)
    lines = [f"| statistic | {names} |", "|---|---|"]
    for label in ABLATION_ROWS:
        cells = [c[label] for c in cols]
        lines.append(f"| {label} | " + " → ".join([*cells[:-1], f"**{cells[-1]}**"]) + " |")
    return "\n".join(lines)


def _args() -> argparse.Namespace:
    default = real_scans_default()
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="pushbroom_demo", help="the push-broom preset")
    ap.add_argument("--spinning", default="demo", help="the spinning-sensor preset beside it")
    ap.add_argument("--seed", type=int, default=0, help="seed of both cities")
    ap.add_argument("--clouds", type=int, default=8, help="synthetic clouds per preset")
    ap.add_argument("--reach", type=float, default=40.0, help="metres of travel each way")
    ap.add_argument("--real", type=Path, default=Path(default), help="the real clouds' folder")
    ap.add_argument("--sample", type=int, default=5000, help="local shapes per cloud")
    ap.add_argument(
        "--ablation",
        action="store_true",
        help="also each distance from the perfect scanner on true poses to the preset",
    )
    return ap.parse_args()


def main() -> int:
    args = _args()
    t0 = time.perf_counter()
    real = real_stats(args.real, args)
    synths, subs = [], []
    for preset in (args.preset, args.spinning):
        stats, sub, sensor = synthetic(preset, args)
        synths.append((f"{preset} {sensor}", stats))
        subs.append((f"{preset} {sensor}", sub))
    print(
        f"seed {args.seed}, {args.clouds} clouds a preset; {time.perf_counter() - t0:.0f} s on "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        file=sys.stderr,
    )
    print(table(real, synths))
    print()
    print(submap_table(subs))
    if args.ablation:
        print()
        print(ablation(real, args.preset, args))
    return 0


if __name__ == "__main__":
    run(main)
