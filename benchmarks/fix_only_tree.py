"""A synthetic city's runs as a fleet with position fixes only: KISS-ICP odometry laid onto
fixes, prepared into a tree that `pnvlad map align` holds to the fixes.

    python benchmarks/fix_only_tree.py --preset demo --scan-spacing 1.0 --out fixdemo/
    pnvlad map align fixdemo/tree -o fixdemo/aligned
    python benchmarks/align_accuracy.py --recorded fixdemo/tree --aligned fixdemo/aligned
    python benchmarks/fix_only_tree.py --accuracy fixdemo/tree fixdemo/aligned

Each run of the preset is driven as `pnvlad synth` drives it (``--scan-spacing`` metres
between scans instead of the preset's: KISS-ICP needs a sensor's rate, not the preset's
sparse scans), its recorded GNSS/INS poses thrown away but their positions at ``--fix-hz``
(the preset's error: a walk of 1.5 m std over 60 m) kept as the fixes. Stage one casts every
scan and runs KISS-ICP on it (``OUT/odometry/<run>.npz``: odometry, fixes, truth; the slow
part, skipped where the file exists); stage two lays the odometry onto the fixes
(``--window``) and prepares the keyframes into ``OUT/tree`` (with ``--gnss-too``, the same
runs from their GNSS/INS poses into ``OUT/tree_gnss``), recording the
simulator's truth in the sidecars as `pnvlad synth` does. Prints per run how far the laid
keyframe poses are from the truth.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from entry import run


def _drive(args: argparse.Namespace, area: int, k: int):  # type: ignore[no-untyped-def]
    from pnvlad_service.synth.generate import _job_drive, _run_jobs_of_area, get_preset

    spec = get_preset(args.preset)
    update = {"scan_spacing": args.scan_spacing, "runs": max(spec.runs, max(args.runs) + 1)}
    spec = spec.model_copy(update=update)
    seed = args.seed
    job = _run_jobs_of_area(Path("."), area, spec.areas[area], spec, seed, {})[k]
    return _job_drive(job), spec.areas[area].name, job["run"], job["run_seed"]


def _fixes(drive, hz: float):  # type: ignore[no-untyped-def]
    from pnvlad_service.data.sources.fixes import Fixes

    t = drive.timestamps
    want = np.arange(t[0], t[-1], round(1e6 / hz))
    idx = np.unique(np.searchsorted(t, want))
    idx = idx[idx < len(t)]
    return Fixes(t[idx], drive.poses[idx, :3, 3].copy(), np.full(len(idx), np.nan))


def odometry_stage(args: argparse.Namespace, area: int, k: int) -> str:
    """Cast every scan of one run and run KISS-ICP over it; save what stage two needs."""
    from pnvlad_service.data.sources.fix_odometry import odometry_poses

    drive, area_name, name, _ = _drive(args, area, k)
    path = args.out / "odometry" / f"{area_name}_{name}.npz"
    if path.is_file():
        return f"{path} (kept)"
    t0 = time.perf_counter()
    odo = odometry_poses(drive, progress=False)
    fixes = _fixes(drive, args.fix_hz)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        path, stamps=drive.timestamps, odometry=odo, truth=drive.true_poses,
        fix_stamps=fixes.stamps, fix_enu=fixes.enu,
    )  # fmt: skip
    return f"{path}: {len(drive)} scans, {len(fixes)} fixes, {time.perf_counter() - t0:.0f} s"


def prepare_stage(args: argparse.Namespace, area: int, k: int) -> str:
    """Lay the saved odometry onto the fixes and prepare the run's keyframes and test submaps."""
    from pnvlad_service.data.prepare import prepare_drive
    from pnvlad_service.data.sources.fix_odometry import FixOdometryDrive
    from pnvlad_service.data.sources.fixes import Fixes

    drive, area_name, name, run_seed = _drive(args, area, k)
    saved = np.load(args.out / "odometry" / f"{area_name}_{name}.npz")
    fixes = Fixes(saved["fix_stamps"], saved["fix_enu"], np.full(len(saved["fix_stamps"]), np.nan))
    fd = FixOdometryDrive(drive, fixes, window_m=args.window, odometry=saved["odometry"])
    t0 = time.perf_counter()
    for tree, lay in (("tree", fd), ("tree_gnss", drive)):
        if tree == "tree_gnss" and not args.gnss_too:
            continue
        prepare_drive(
            lay, args.out / tree / area_name / name, kinds=("keyframe",),
            seed=run_seed % (2**31), progress=False, overwrite=True,
        )  # fmt: skip
    err = np.linalg.norm(fd.poses[:, :2, 3] - saved["truth"][:, :2, 3], axis=1)
    rec = np.linalg.norm(drive.poses[:, :2, 3] - saved["truth"][:, :2, 3], axis=1)
    return (
        f"{area_name}/{name}: laid poses off the truth median {np.median(err):.2f} m, "
        f"p99 {np.percentile(err, 99):.2f} m (the GNSS/INS recording: {np.median(rec):.2f}, "
        f"{np.percentile(rec, 99):.2f}); prepared in {time.perf_counter() - t0:.0f} s"
    )


def accuracy(recorded: Path, aligned: Path) -> None:
    """The keyframes' position error against the truth (m) in ``aligned``, for the runs that
    hold fixes only in ``recorded`` and for the others, each run and each group."""
    from pnvlad_service.data.tree import BenchmarkTree

    tree = BenchmarkTree(aligned)
    groups: dict[str, list[float]] = {"fixes only": [], "GNSS/INS": []}
    for dataset in tree.datasets:
        for name in tree.runs(dataset):
            frames = tree.frames(dataset, name, "keyframe") or []
            err = [float(np.linalg.norm(f.origin[:2] - f.true_position[:2])) for f in frames]
            fixes = (recorded / dataset / name / "fixes.csv").is_file()
            groups["fixes only" if fixes else "GNSS/INS"] += err
            print(f"{dataset}/{name} ({'fixes only' if fixes else 'GNSS/INS'}): " + _q(err))
    for group, err in groups.items():
        if err:
            print(f"all {group} runs: " + _q(err))


def _q(err: list[float]) -> str:
    p = np.percentile(err, [50, 90, 99])
    q = f"median {p[0]:.2f} p90 {p[1]:.2f} p99 {p[2]:.2f} max {max(err):.2f} m"
    return f"{len(err)} keyframes, {q}"


def main() -> int:
    from pnvlad_service.synth.generate import get_preset

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scan-spacing", type=float, default=1.0, help="metres between scans")
    ap.add_argument("--fix-hz", type=float, default=1.0, help="fixes a second")
    ap.add_argument("--window", type=float, default=50.0, help="the fit's window (m)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", default=None, help="run indices, e.g. 4,5 (default: the preset's)")
    ap.add_argument(
        "--gnss-too", action="store_true", help="also prepare the runs from their GNSS/INS poses"
    )
    ap.add_argument("--stage", choices=("odometry", "prepare", "both"), default="both")
    ap.add_argument("--out", type=Path, help="where the odometry and the trees go")
    ap.add_argument(
        "--accuracy", type=Path, nargs=2, metavar=("RECORDED", "ALIGNED"),
        help="only print an aligned tree's keyframe error, fix-only runs apart",
    )  # fmt: skip
    args = ap.parse_args()
    if args.accuracy:
        accuracy(*args.accuracy)
        return 0
    spec = get_preset(args.preset)
    ks = range(spec.runs) if args.runs is None else [int(k) for k in args.runs.split(",")]
    args.runs = list(ks)
    runs = [(a, k) for a in range(len(spec.areas)) for k in ks]
    stages = (
        [odometry_stage, prepare_stage]
        if args.stage == "both"
        else ([odometry_stage] if args.stage == "odometry" else [prepare_stage])
    )
    for stage in stages:
        with ProcessPoolExecutor(args.workers) as pool:
            for line in pool.map(stage, *zip(*[(args, a, k) for a, k in runs], strict=True)):
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(run(main))
