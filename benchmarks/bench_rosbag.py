"""Throughput of preparing a drive from a ROS bag against the KITTI path on the same scans.

Usage: python benchmarks/bench_rosbag.py [--frames 60] [--repeats 3] [--scans DIR] [--work DIR]

Builds a KITTI-style sequence of the real KITTI scans (the two of ../shared/data/real_scans,
alternating, 1.5 m apart, full resolution) and writes the same scans and poses as a ROS 1 bag, a
ROS 2 sqlite3 bag and a ROS 2 mcap bag (PointCloud2 x, y, z, intensity + Odometry). Then, one
after the other on the same machine, it prepares each (``prepare_drive``, both kinds, the CLI's
defaults) and prints per source: the time to open the drive (for a bag: indexing the clouds and
reading the poses), the time to prepare, scans read per second and submaps per second (median of
``--repeats``, after an untimed warm-up run), and checks that every bag gave the KITTI path's
bytes. A second table times reading alone: every scan of the drive once, in order, without the
filter G.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from entry import real_scans_default, run

from pnvlad_service.extras import require

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # tests.data.sources.test_rosbag's bag builders

FORMATS = [
    ("ROS 1 .bag", 1, "sqlite3", "drive.bag"),
    ("ROS 2 sqlite3", 2, "sqlite3", "db3"),
    ("ROS 2 mcap", 2, "mcap", "mcap"),
]


def tree_bytes(run: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(run)): p.read_bytes()
        for p in sorted(run.rglob("*"))
        if p.is_file() and not p.name.startswith(".")
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=3)
    default = real_scans_default()
    parser.add_argument("--scans", type=Path, default=Path(default))
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: tmp)")
    args = parser.parse_args()
    require("rosbags", "rosbags", "rosbag", "Writing and reading ROS bags")

    from pnvlad_service.data.prepare import prepare_drive
    from pnvlad_service.data.sources.kitti import KittiSequence
    from pnvlad_service.data.sources.rosbag import RosbagDrive
    from tests.data.sources.test_rosbag import EPOCH_US, KITTI_POINT, STEP_M, bag_of_sequence

    work = Path(tempfile.mkdtemp(dir=args.work))
    try:
        seq = work / "seq"
        (seq / "velodyne").mkdir(parents=True)
        scans = [np.fromfile(args.scans / f"kitti00_00000{k}.bin", KITTI_POINT) for k in (0, 5)]
        for i in range(args.frames):
            scans[i % 2].tofile(seq / "velodyne" / f"{i:06d}.bin")
        (seq / "poses.txt").write_text(
            "".join(f"1 0 0 0 0 1 0 0 0 0 1 {STEP_M * i!r}\n" for i in range(args.frames))
        )
        (seq / "times.txt").write_text("".join(f"{0.1 * i:.6f}\n" for i in range(args.frames)))
        sources = {"KITTI sequence": lambda: KittiSequence(seq, time_offset_us=EPOCH_US)}
        sizes = {"KITTI sequence": sum(f.stat().st_size for f in (seq / "velodyne").iterdir())}
        for label, ros, storage, name in FORMATS:
            path = bag_of_sequence(work / name, seq, ros=ros, storage=storage)
            sizes[label] = (
                sum(f.stat().st_size for f in path.rglob("*"))
                if path.is_dir()
                else path.stat().st_size
            )
            sources[label] = lambda p=path: RosbagDrive(p, "/velodyne_points", pose_topic="/odom")
        print(
            f"{args.frames} scans of {len(scans[0]):,} / {len(scans[1]):,} points "
            f"(KITTI .bin files: {sizes['KITTI sequence'] / 1e6:.0f} MB)"
        )
        print(
            f"{'source':<16}{'MB':>6}{'open s':>9}{'prepare s':>11}{'scans/s':>9}"
            f"{'submaps/s':>11}  same bytes"
        )
        reference = None
        prepare_drive(sources["KITTI sequence"](), work / "warm-up", progress=False)  # imports
        for label, make in sources.items():
            opens, preps, rates, subs = [], [], [], []
            for r in range(args.repeats):
                out = work / f"run_{r}"
                t0 = time.perf_counter()
                drive = make()
                t1 = time.perf_counter()
                result = prepare_drive(drive, out, progress=False)
                t2 = time.perf_counter()
                getattr(drive, "close", lambda: None)()
                opens.append(t1 - t0)
                preps.append(t2 - t1)
                rates.append(result.scans_read / (t2 - t0))
                subs.append(sum(x.written for x in result.layouts) / (t2 - t0))
                got = tree_bytes(out)
                shutil.rmtree(out)
            reference = reference or got
            same = "yes" if got == reference else "NO"
            print(
                f"{label:<16}{sizes[label] / 1e6:>6.0f}{statistics.median(opens):>9.2f}"
                f"{statistics.median(preps):>11.2f}{statistics.median(rates):>9.1f}"
                f"{statistics.median(subs):>11.2f}  {same}"
            )
        print(f"\nreading only (every scan once, in order, no G; median of {args.repeats})")
        print(f"{'source':<16}{'open s':>9}{'read s':>9}{'scans/s':>9}")
        for label, make in sources.items():
            opens, reads = [], []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                drive = make()
                t1 = time.perf_counter()
                for i in range(len(drive)):
                    drive.scan(i)
                t2 = time.perf_counter()
                getattr(drive, "close", lambda: None)()
                opens.append(t1 - t0)
                reads.append(t2 - t1)
            total = statistics.median(o + r for o, r in zip(opens, reads, strict=True))
            print(
                f"{label:<16}{statistics.median(opens):>9.2f}{statistics.median(reads):>9.2f}"
                f"{args.frames / total:>9.1f}"
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    run(main)
