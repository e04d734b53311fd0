"""Every run of a `pnvlad synth` tree replayed as a ROS bag against a map of the others (#34).

For each run of each area (or those named): a keyframe bundle of the area's other runs
(``pnvlad index build --layout keyframe``, cached under OUT/maps), the run written as a ROS 2
bag holding every ``--every``-th scan (``/points``, and the true poses on ``/ground_truth``, as
``benchmarks/make_rosbag.py`` writes them), then ``pnvlad localize --rosbag BAG --index MAP``
(the replay CLI, in this process) asks with each scan as a raw single scan. Prints one row a run
(the share of answers within 25 m, verified, the median error of the verified poses and the
verified poses more than 5 m off) and the totals; the CSVs and PNGs stay in OUT/replays.

    python benchmarks/replay_benchmark.py --root B --model runs/bev_scan/model --out out/replay
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
from entry import run

from pnvlad_service.extras import require


class EveryNth:
    """Scans 0, n, 2n, ... of a drive: ``poses`` the recorded (GNSS/INS) ones, ``true`` the
    simulator's."""

    def __init__(self, drive, n: int) -> None:
        self.drive, self.name = drive, drive.name
        self.index = np.arange(0, len(drive), n)
        self.timestamps = drive.timestamps[self.index]
        self.poses = drive.poses[self.index]
        self.true = drive.true_poses[self.index]

    def __len__(self) -> int:
        return len(self.index)

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(int(self.index[i]))


def replay_run(root: Path, model: Path, out: Path, area: str, name: str, every: int) -> dict:
    """Bundle, bag and replay of one run; its figures."""
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.build import build_bundle
    from pnvlad_service.synth.generate import simulated_drive
    from pnvlad_service.synth.windows import drives_of

    tree = BenchmarkTree(root)
    bundle = out / "maps" / area / f"{name}.index"
    if not (bundle / "manifest.json").is_file():
        others = [r for r in tree.runs(area) if r != name]
        build_bundle(bundle, model, root, datasets=[area], runs=others, layout="keyframe",
                     progress=False)  # fmt: skip
    drive = simulated_drive(*drives_of(root)[(area, name)])
    east, north = (float(v) for v in drive.world.origin)
    bag = out / "bags" / area / name
    if not (bag / "metadata.yaml").is_file():
        bag.parent.mkdir(parents=True, exist_ok=True)
        sub = EveryNth(drive, every)
        write_drive_bag(sub, bag, origin_ne=(north, east), truth=sub.true, progress=False)
    dest = out / "replays" / area / name
    dest.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    args = ["localize", "--rosbag", str(bag), "--cloud-topic", "/points",
            "--pose-topic", "/ground_truth", "--origin", f"{north!r},{east!r}", "--every", "1",
            "--index", str(bundle), "-m", str(model), "--out", str(dest),
            "--no-progress"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    if res.exit_code != 0:
        raise SystemExit(f"replay of {area}/{name} failed:\n{res.output}")
    seconds = time.perf_counter() - t0
    with open(f"{dest}.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    errors = np.array([float(r["error_m"]) for r in rows if r["error_m"]])
    ver = [r for r in rows if r["verified"] == "true"]
    pose_err = np.array([float(r["pose_error_m"]) for r in ver if r["pose_error_m"]])
    return {
        "area": area,
        "run": name,
        "queries": len(rows),
        "within": int((errors <= 25.0).sum()),
        "verified": len(ver),
        "median_pose_m": float(np.median(pose_err)) if len(pose_err) else float("nan"),
        "wrong_verified": int((pose_err > 5.0).sum()),
        "median_error_m": float(np.median(errors)) if len(errors) else float("nan"),
        "seconds": seconds,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, required=True, help="a pnvlad synth tree")
    ap.add_argument("--model", type=Path, required=True, help="a single-scan model")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--every", type=int, default=10, help="every Nth scan of a run (default 10)")
    ap.add_argument("--area", action="append", help="only this area (repeatable)")
    ap.add_argument("--run", action="append", help="only this run (repeatable)")
    args = ap.parse_args()
    require("rosbags", "rosbags", "rosbag", "Replaying bags")

    from pnvlad_service.data.tree import BenchmarkTree

    tree = BenchmarkTree(args.root)
    figures = []
    for area in args.area or tree.datasets:
        for name in tree.runs(area):
            if args.run and name not in args.run:
                continue
            f = replay_run(args.root, args.model, args.out, area, name, args.every)
            figures.append(f)
            print(
                f"{area:<12} {name}  {f['within']:3d}/{f['queries']:3d} within 25 m, "
                f"{f['verified']:3d} verified, verified poses {f['median_pose_m']:.2f} m "
                f"(median), {f['wrong_verified']} more than 5 m off; {f['seconds']:.0f} s",
                flush=True,
            )
    q = sum(f["queries"] for f in figures)
    within = sum(f["within"] for f in figures)
    ver = sum(f["verified"] for f in figures)
    wrong = sum(f["wrong_verified"] for f in figures)
    med = float(np.median([f["median_pose_m"] for f in figures]))
    print(
        f"all {len(figures)} runs: {within}/{q} within 25 m ({100 * within / q:.1f} %), {ver} "
        f"verified ({100 * ver / q:.1f} %), {wrong} verified poses more than 5 m off; median of "
        f"the runs' median pose errors {med:.2f} m"
    )
    return 0


if __name__ == "__main__":
    run(main)
