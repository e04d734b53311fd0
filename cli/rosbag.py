"""The ROS bag options shared by `pnvlad data prepare --rosbag` and `pnvlad localize --rosbag`.

Options are declared once here (so ``--cloud-topic`` means the same in both commands) with the
helpers that turn them into a :class:`pnvlad_service.data.sources.rosbag.RosbagDrive` (through the
drive sources' registry, :mod:`pnvlad_service.data.sources.registry`) and print a bag's topics
(``--list``). Library imports happen inside the functions so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from pnvlad_service.data.sources.rosbag import RosbagDrive

PANEL = "ROS bag"

ROSBAG = typer.Option(
    None,
    "--rosbag",
    help="ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap (needs the 'rosbag' extra). Use with "
    "--cloud-topic and --pose-topic or --tf; `pnvlad data prepare --rosbag BAG --list` shows "
    "its topics.",
    rich_help_panel=PANEL,
)
CLOUD_TOPIC = typer.Option(
    None,
    "--cloud-topic",
    help="With --rosbag: the sensor_msgs/PointCloud2 topic (x, y, z float32 or float64).",
    rich_help_panel=PANEL,
)
POSE_TOPIC = typer.Option(
    None,
    "--pose-topic",
    help="With --rosbag: a nav_msgs/Odometry, geometry_msgs/PoseStamped or "
    "PoseWithCovarianceStamped topic, interpolated to each scan's time.",
    rich_help_panel=PANEL,
)
TF_FRAME = typer.Option(
    None,
    "--tf",
    help="With --rosbag, instead of --pose-topic: pose the clouds by /tf (+ /tf_static) from "
    "this fixed frame (e.g. odom or map).",
    rich_help_panel=PANEL,
)
MAX_POSE_GAP = typer.Option(
    None,
    "--max-pose-gap",
    help="With --rosbag: drop scans between two pose samples more than this many seconds "
    "apart (default 2; 0: interpolate across any gap).",
    rich_help_panel=PANEL,
)
FIX_TOPIC = typer.Option(
    None,
    "--fix-topic",
    help="With --rosbag and --odometry kiss-icp, instead of --pose-topic or --tf: a "
    "sensor_msgs/NavSatFix topic (positions only, e.g. /fix); the scans' KISS-ICP odometry is "
    "laid onto the fixes (needs --utm-zone) and the fixes are kept beside the run for "
    "`pnvlad map align`.",
    rich_help_panel=PANEL,
)
ODOMETRY = typer.Option(
    None,
    "--odometry",
    help="With --fix-topic: kiss-icp, the LiDAR odometry that poses the scans between and "
    "beside the fixes (needs the 'odometry' extra).",
    rich_help_panel=PANEL,
)
LIST = typer.Option(
    False,
    "--list",
    help="With --rosbag: print the bag's topics with message types and counts, and stop.",
    rich_help_panel=PANEL,
)


def check_unused(rosbag: Path | None, **options: object) -> None:
    """InputError when a bag-only option is given without ``--rosbag``."""
    from pnvlad_service.errors import InputError

    if rosbag is not None:
        return
    for flag, value in options.items():
        if value not in (None, False):
            name = "--" + flag.replace("_", "-")
            raise InputError("applies to --rosbag only", name)


def open_drive(
    rosbag: Path,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    *,
    origin_ne: tuple[float, float] = (0.0, 0.0),
    yaw_deg: float = 0.0,
    max_pose_gap: float | None = None,
) -> RosbagDrive:
    """The drive of ``--rosbag`` with its topics (the registry's ``rosbag`` source);
    InputError naming the missing option."""
    from pnvlad_service.data.sources.registry import DriveOptions, open_drive

    options = DriveOptions(
        cloud_topic=cloud_topic,
        pose_topic=pose_topic,
        tf_frame=tf_frame,
        origin_ne=origin_ne,
        yaw_deg=yaw_deg,
        max_pose_gap=max_pose_gap,
    )
    return open_drive("rosbag", rosbag, options)  # type: ignore[return-value]


def print_topics(rosbag: Path) -> None:
    """``--list``: the bag's topics, types and counts, and which options each suits."""
    from pnvlad_service.data.sources.rosbag import CLOUD_TYPE, POSE_TYPES, TF_TYPE, list_topics

    topics = list_topics(rosbag)
    width = max([len(t.name) for t in topics] + [5])
    types = max([len(t.msgtype or "") for t in topics] + [4])
    typer.echo(f"{'TOPIC':<{width}}  {'TYPE':<{types}}  {'MESSAGES':>9}  USE WITH")
    for t in topics:
        use = ""
        if t.msgtype == CLOUD_TYPE:
            use = "--cloud-topic"
        elif t.msgtype in POSE_TYPES:
            use = "--pose-topic"
        elif t.msgtype == TF_TYPE:
            use = "--tf FRAME"
        msgtype = t.msgtype or "(several types)"
        typer.echo(f"{t.name:<{width}}  {msgtype:<{types}}  {t.count:>9,}  {use}")
