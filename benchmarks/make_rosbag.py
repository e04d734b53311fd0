"""Write a ROS bag from a synthetic run, to try the rosbag drive and the replay without data.

Usage: python benchmarks/make_rosbag.py --out city.bag [--preset demo] [--area 0] [--run 0]
       [--seed 0] [--storage sqlite3|mcap] [--max-scans N] [--tf]
       [--off-map METRES [--back METRES]] [--kidnap AT_S:GAP_S [--hide-gap]]
       [--beams N --columns N]

Rebuilds one run of ``pnvlad synth`` (:func:`pnvlad_service.synth.generate.simulated_drive`:
same city, route and seed as the tree ``pnvlad synth --preset PRESET --seed SEED`` writes)
and writes it as a bag: ``/points`` (sensor_msgs/PointCloud2, float32 x, y, z, frame
``lidar``), ``/odom`` (nav_msgs/Odometry: the run's GNSS/INS poses, errors included, in an
``odom`` frame whose origin is the area's UTM origin), ``/ground_truth`` (Odometry: the true
poses) and, with ``--tf``, ``/tf`` (odom <- lidar). A path ending in ``.bag`` is a ROS 1 bag,
anything else a ROS 2 bag folder. It prints the commands that read the bag back.

Drives that test a localiser (:mod:`pnvlad_service.synth.excursions`): ``--off-map METRES``
drives the run's route, METRES further through streets the route never takes (off a map made
of the area's runs), turns and comes back onto the route for ``--back`` metres (default 200);
``--kidnap AT_S:GAP_S`` drops the scans of GAP_S seconds from AT_S on (the robot carried
elsewhere: ``/odom`` goes on from where it was, ``/ground_truth`` jumps; ``--hide-gap``: the
clock does not jump either). ``--beams`` / ``--columns`` cast the scans with another sensor
(64 x 2,600 rays give about 120,000 points, a KITTI HDL-64E scan's count; the presets cast a
few thousand).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from entry import run

from pnvlad_service.extras import require


def true_poses(drive) -> np.ndarray:
    """float64 [T, 4, 4] sensor -> UTM from a SimulatedDrive's true position and heading."""
    t_count = len(drive)
    poses = np.tile(np.eye(4), (t_count, 1, 1))
    c, s = np.cos(drive.true_yaw), np.sin(drive.true_yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, 0, 3] = drive.world.origin[0] + drive.true_xy[:, 0]
    poses[:, 1, 3] = drive.world.origin[1] + drive.true_xy[:, 1]
    poses[:, 2, 3] = drive.true_z
    return poses


class FirstScans:
    """The first ``n`` scans of a drive, as a drive."""

    def __init__(self, drive, n: int) -> None:
        self.drive, self.n = drive, min(n, len(drive))
        self.name = drive.name
        self.timestamps = drive.timestamps[: self.n]
        self.poses = drive.poses[: self.n]

    def __len__(self) -> int:
        return self.n

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(i)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="NAME.bag (ROS 1) or a folder")
    parser.add_argument("--preset", default="demo", help="tiny, demo or benchmark")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--area", type=int, default=0, help="area index of the preset")
    parser.add_argument("--run", type=int, default=0, help="run index within the area")
    parser.add_argument("--storage", choices=["sqlite3", "mcap"], default="sqlite3")
    parser.add_argument("--max-scans", type=int, default=0, help="only the first N (0: all)")
    parser.add_argument("--tf", action="store_true", help="also write the poses on /tf")
    parser.add_argument(
        "--off-map",
        type=float,
        default=0.0,
        metavar="METRES",
        help="drive this far beyond the route's end (off the map) and back",
    )
    parser.add_argument(
        "--back",
        type=float,
        default=200.0,
        metavar="METRES",
        help="with --off-map: metres driven back along the route",
    )
    parser.add_argument(
        "--kidnap",
        default=None,
        metavar="AT_S:GAP_S",
        help="drop GAP_S seconds of scans from AT_S on (a kidnapped robot)",
    )
    parser.add_argument(
        "--hide-gap",
        action="store_true",
        help="with --kidnap: the clock does not jump over the gap either",
    )
    parser.add_argument("--beams", type=int, default=0, help="cast with this many beams")
    parser.add_argument("--columns", type=int, default=0, help="... and columns (rays a turn)")
    args = parser.parse_args()
    require("rosbags", "rosbags", "rosbag", "Writing ROS bags")  # before minutes of simulation

    from pnvlad_service.data.sources.rosbag_write import write_drive_bag
    from pnvlad_service.synth.generate import get_preset, simulated_drive
    from pnvlad_service.synth.sensors import LidarConfig

    spec = get_preset(args.preset)
    dense = {k: v for k, v in (("beams", args.beams), ("columns", args.columns)) if v}
    if dense:
        spec = spec.model_copy(
            update={
                "lidar": spec.lidar.model_copy(update=dense),
                "lidars": [
                    LidarConfig.model_validate({**s.model_dump(), "elevations_deg": None, **dense})
                    for s in spec.lidars
                ],
            }
        )
    if args.off_map:
        from pnvlad_service.synth.excursions import off_map_drive

        drive = off_map_drive(spec, args.area, args.run, args.seed, args.off_map, args.back)
    else:
        drive = simulated_drive(spec, args.area, args.run, args.seed)
    truth = true_poses(drive)
    if args.kidnap:
        from pnvlad_service.synth.excursions import Kidnapped

        at_s, gap_s = (float(v) for v in args.kidnap.split(":"))
        drive = Kidnapped(drive, at_s, gap_s, hide_gap=args.hide_gap)
        truth = drive.true_poses
        print(
            f"kidnapped: scans {drive.gap_index - 1} and {drive.gap_index} of the bag are "
            f"{gap_s:g} s of driving apart"
        )
    if args.max_scans:
        drive = FirstScans(drive, args.max_scans)
        truth = truth[: len(drive)]
    inner = drive
    while not hasattr(inner, "world"):
        inner = inner.drive
    east, north = (float(v) for v in inner.world.origin)
    started = time.perf_counter()
    write_drive_bag(
        drive,
        args.out,
        origin_ne=(north, east),
        truth=truth,
        tf_topic="/tf" if args.tf else None,
        storage=args.storage,
        progress=True,
    )
    seconds = time.perf_counter() - started
    size = (
        sum(f.stat().st_size for f in args.out.rglob("*"))
        if args.out.is_dir()
        else (args.out.stat().st_size)
    )
    print(
        f"{args.out}: {len(drive)} scans of run {drive.name} ({args.preset}, area {args.area}, "
        f"seed {args.seed}), {size / 1e6:.1f} MB in {seconds:.1f} s"
    )
    print("read it back with:")
    print(f"  pnvlad data prepare --rosbag {args.out} --list")
    print(
        f"  pnvlad data prepare --rosbag {args.out} --cloud-topic /points --pose-topic /odom "
        f"--origin {north:.3f},{east:.3f} --out bench/city/{drive.name}"
    )
    print(
        f"  pnvlad localize --rosbag {args.out} --cloud-topic /points --pose-topic /odom "
        f"--truth-topic /ground_truth --origin {north:.3f},{east:.3f} --index MAP"
    )


if __name__ == "__main__":
    run(main)
