"""`pnvlad localize --rosbag` / `--kitti`: a drive against the service, a CSV and a PNG.

The options of `pnvlad localize`'s two drive modes (cli/localize.py): ``follow`` (the default:
every scan goes to the drive localiser, which searches until a fix is confirmed, then tracks
by registration near the pose its odometry predicts, and says when it is lost) and
``per-scan`` (every Nth scan asked alone). The command fills a
:class:`~pnvlad_service.localization.drive.config.DriveConfig` (:func:`drive_config`) and
calls :func:`run`, which opens the source (:func:`open_source`, the one place that knows the
kinds of drive) and the service, and hands both to
:func:`pnvlad_service.localization.drive.job.run_job`. Library imports happen inside the
functions so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from pnvlad_cli import rosbag as bag_options

if TYPE_CHECKING:
    from pnvlad_service.localization.drive.config import DriveConfig, ServiceConfig, SourceConfig

PANEL = "Replay (with --rosbag)"

ORIGIN = typer.Option(
    None,
    "--origin",
    help="With --rosbag and poses: UTM NORTHING,EASTING of the pose frame's origin (default 0,0).",
    rich_help_panel=PANEL,
)
YAW = typer.Option(
    0.0,
    "--yaw",
    help="With --rosbag and poses: direction of the pose frame's x axis, degrees "
    "counter-clockwise from east.",
    rich_help_panel=PANEL,
)
EVERY = typer.Option(
    None,
    "--every",
    help="With --rosbag: use every Nth scan (default: every scan when following, 10 with "
    "--per-scan).",
    rich_help_panel=PANEL,
)
FOLLOW = typer.Option(
    None,
    "--follow/--per-scan",
    help="With --rosbag or --kitti: follow the drive (search until a fix is confirmed by the "
    "odometry, then track by registration near the prediction, say when lost; default), or "
    "ask with every Nth scan alone: --mode follow or --mode per-scan.",
    rich_help_panel=PANEL,
    show_default=False,
)
TRUTH_TOPIC = typer.Option(
    None,
    "--truth-topic",
    help="With --rosbag: a pose topic of the drive's true poses (e.g. /ground_truth), for the "
    "errors; default: the --pose-topic / --tf poses.",
    rich_help_panel=PANEL,
)
ODOMETRY = typer.Option(
    "auto",
    "--odometry",
    help="Following: the motion between scans from 'poses' (--pose-topic / --tf, or the KITTI "
    "poses), 'registered' (those poses' steps refined by registering each scan onto the one "
    "before it: centimetres where a GNSS/INS step is decimetres off), 'kiss-icp' (LiDAR "
    "odometry on the scans, extra 'odometry') or 'none' (constant velocity); 'auto': "
    "registered when poses are given, else kiss-icp when installed, else none.",
    rich_help_panel=PANEL,
)
WINDOW = typer.Option(
    None,
    "--window",
    help="With --per-scan: ask with the last METRES of driving laid together (kind window, the "
    "way pnvlad data prepare lays a submap), posed by --pose-topic / --tf or, with --odometry "
    "kiss-icp, by LiDAR odometry; for a map of submaps.",
    rich_help_panel=PANEL,
)
RADIUS = typer.Option(
    None,
    "--radius",
    help="Following: map entries within this many metres of the predicted pose are registered "
    "to (default 20).",
    rich_help_panel=PANEL,
)
CONFIRM = typer.Option(
    None,
    "--confirm",
    help="Following: verified answers that must agree with the odometry before a fix is "
    "accepted (default 2).",
    rich_help_panel=PANEL,
)
FAILURES = typer.Option(
    None,
    "--failures",
    help="Following: failed registrations in a row that make the localiser lost (default 3).",
    rich_help_panel=PANEL,
)
FUSE = typer.Option(
    None,
    "--fuse/--no-fuse",
    help="Following: weigh each registration against the odometry's prediction by their "
    "covariances, so that a street the map leaves loose along it keeps the odometry's "
    "position there (default: with --odometry registered, the pose topic's steps refined by "
    "the scans; not with the recorded steps alone, which are decimetres off).",
    rich_help_panel=PANEL,
)
ALIGNED_MAP = typer.Option(
    None,
    "--aligned-map/--no-aligned-map",
    help="Following with --index: register each scan to the 8 nearest entries of any of the "
    "map's drives (they agree), a fit under the threshold once more to 24, or (--no-aligned-map) "
    "to 4 of one drive. Default: as the bundle records; index build of a tree made by pnvlad "
    "map align records its map as aligned.",
    show_default=False,
    rich_help_panel=PANEL,
)
OUT = typer.Option(
    None,
    "--out",
    "-o",
    help="With --rosbag or --kitti: write OUT.csv (one row a scan) and OUT.png (default: the "
    "drive's name beside it, e.g. drive.follow.csv, or drive.replay.csv with --per-scan).",
    rich_help_panel=PANEL,
)
MAP = typer.Option(
    None,
    "--map",
    help="With --rosbag --url: a copy of the server's bundle, to draw the map's submaps in "
    "the PNG (with --index the bundle is used).",
    rich_help_panel=PANEL,
)
KITTI = typer.Option(
    None,
    "--kitti",
    help="Follow a KITTI odometry sequence folder (velodyne/*.bin, poses.txt, optional "
    "times.txt and calib.txt) as a drive: its poses are the odometry and the truth; "
    "--origin and --yaw place it in UTM.",
    rich_help_panel=PANEL,
)
PLOT = typer.Option(
    True,
    "--plot/--no-plot",
    help="With --rosbag: write the PNG (needs the 'plot' extra).",
    rich_help_panel=PANEL,
)

VIEW_PANEL = "Live view and robotics outputs (with --rosbag or --kitti)"
FOXGLOVE = typer.Option(
    None,
    "--foxglove",
    help="Stream the drive live to Foxglove (the app connects to ws://HOST:PORT): the map, each "
    "scan at its pose, the pose and its covariance, the truth, the paths, the state, /tf. "
    "HOST:PORT, or :PORT on 127.0.0.1 (8765 by default); needs the 'view' extra.",
    rich_help_panel=VIEW_PANEL,
)
MCAP = typer.Option(
    None,
    "--mcap",
    help="Write what the live view streams to this MCAP file, for Foxglove to open later.",
    rich_help_panel=VIEW_PANEL,
)
ROS2_BAG = typer.Option(
    None,
    "--ros2-bag",
    help="Write a ROS 2 bag folder (MCAP storage) of the poses with their covariance "
    "(PoseWithCovarianceStamped on /pnvlad/pose), the path, NavSatFix and /tf, for ros2 bag play.",
    rich_help_panel=VIEW_PANEL,
)
TRAJECTORIES = typer.Option(
    None,
    "--trajectories",
    help="Write the pose and the truth as TUM (STEM.tum, STEM.truth.tum) and KITTI files "
    "(STEM.kitti, STEM.truth.kitti, STEM.kitti.times) that evo_traj / evo_ape read.",
    rich_help_panel=VIEW_PANEL,
)
UTM_ZONE = typer.Option(
    None,
    "--utm-zone",
    help="The map's UTM zone (e.g. 32U, '17 south') when its bundle does not record one: the "
    "outputs then carry latitude and longitude.",
    rich_help_panel=VIEW_PANEL,
)


def check_per_scan(
    truth_topic: str | None,
    odometry: str,
    radius: float | None,
    confirm: int | None,
    failures: int | None,
    window: float | None = None,
    fuse: bool | None = None,
) -> None:
    """InputError when an option of following is given with ``--per-scan`` (``--odometry``
    goes with ``--window``: it poses the window; the window's own checks are the config's)."""
    from pnvlad_service.errors import InputError

    given = {
        "--truth-topic": truth_topic,
        "--radius": radius,
        "--confirm": confirm,
        "--failures": failures,
        "--fuse": fuse,
        "--odometry": None if odometry == "auto" or window is not None else odometry,
    }
    for flag, value in given.items():  # fmt: skip
        if value is not None:
            raise InputError("applies to following a drive (not with --per-scan)", flag)


def view_outputs(
    foxglove: str | None,
    mcap: Path | None,
    ros2_bag: Path | None,
    trajectories: Path | None,
    utm_zone: str | None,
) -> dict[str, Any]:
    """The output section's robotics outputs from the options (``--foxglove`` parsed as
    HOST:PORT)."""
    from pnvlad_service.localization.outputs.foxglove_view import parse_host_port

    return {
        "foxglove": None if foxglove is None else parse_host_port(foxglove),
        "mcap": mcap, "ros2_bag": ros2_bag, "trajectories": trajectories, "utm_zone": utm_zone,
    }  # fmt: skip


def parse_origin(text: str | None) -> tuple[float, float]:
    """``--origin`` NORTHING,EASTING -> (northing, easting); (0, 0) when not given."""
    if text is None:
        return (0.0, 0.0)
    from pnvlad_cli.data_prepare import _parse_origin

    return _parse_origin(text)


#: The option of each field of a DriveConfig that the library names in its errors.
FLAGS = {
    "every": "--every",
    "odometry": "--odometry",
    "window_m": "--window",
    "tracking.radius_m": "--radius",
    "tracking.confirm": "--confirm",
    "tracking.failures": "--failures",
    "tracking.fuse": "--fuse",
}


@contextmanager
def flags() -> Iterator[None]:
    """The library's errors that name a field of the config, naming its option instead."""
    from pydantic import ValidationError

    from pnvlad_service.errors import InputError
    from pnvlad_service.localization.drive.config import config_error

    try:
        yield
    except ValidationError as exc:
        err = config_error(exc)
        raise InputError(err.detail, FLAGS.get(err.source or "", err.source)) from None
    except InputError as exc:
        if exc.source not in FLAGS:
            raise
        raise InputError(exc.detail, FLAGS[exc.source]) from None


def drive_config(policy: str, *, tracking: dict[str, Any], **sections: Any) -> DriveConfig:
    """The :class:`~pnvlad_service.localization.drive.config.DriveConfig` of the options
    (``tracking``: the tracker's rules given, ``None`` for its defaults)."""
    from pnvlad_service.localization.drive.config import DriveConfig

    given = {k: v for k, v in tracking.items() if v is not None}
    with flags():
        return DriveConfig(policy=policy, tracking=given, **sections)  # type: ignore[arg-type]


def run(config: DriveConfig) -> None:
    """The whole drive: open the source and the service, run it, print what it made."""
    from pnvlad_service.localization.drive.job import run_job

    with flags():
        config.check()
        drive, where, truth = open_source(config.source)
        try:
            with open_service(config.service) as service:
                result = run_job(config, drive, service, source=where, truth=truth)
        finally:
            close = getattr(drive, "close", None)
            if close is not None:
                close()
    for line in result.lines():
        typer.echo(line)
    for error in result.errors:
        typer.secho(f"error: {error}", err=True, fg=typer.colors.RED)
    if result.errors:
        raise typer.Exit(code=2)


@contextmanager
def open_service(config: ServiceConfig) -> Iterator[Any]:
    """The :class:`~pnvlad_service.localization.drive.service.Service` of a server
    (``--url``) or of a bundle in this process (``--index``)."""
    from pnvlad_service.localization.drive import service

    if config.url is not None:
        from pnvlad_service.client import LocalizeClient

        with LocalizeClient(config.url, api_key=config.api_key) as client:
            yield service.http_service(client, config.top_n)
        return
    from pnvlad_service.localization.query.localizer import Localizer

    assert config.index is not None
    with Localizer.load(config.index, config.model, config.localizer_config()) as loc:
        yield service.local_service(loc, config.index, config.top_n)


def open_source(source: SourceConfig) -> tuple[Any, Path, Any]:
    """(the drive, the file or folder it came from, its true poses from ``--truth-topic`` or
    ``None``): the KITTI sequence, or the bag's clouds with the poses of ``--pose-topic`` /
    ``--tf`` when given, each opened by the registry of drive sources
    (:mod:`pnvlad_service.data.sources.registry`)."""
    from pnvlad_service.data.sources.registry import DriveOptions, open_drive
    from pnvlad_service.errors import InputError

    if source.kitti is not None:
        if source.truth_topic is not None:
            raise InputError("applies to --rosbag only (a KITTI sequence's poses are its truth)",
                             "--truth-topic")  # fmt: skip
        placed = DriveOptions(origin_ne=source.origin_ne, yaw_deg=source.yaw_deg)
        return open_drive("kitti", source.kitti, placed), source.kitti, None
    assert source.rosbag is not None
    if source.pose_topic is None and source.tf_frame is None:
        if source.cloud_topic is None:
            raise InputError("--rosbag needs --cloud-topic (see `pnvlad data prepare "
                             "--rosbag BAG --list`)", "--cloud-topic")  # fmt: skip
        clouds = DriveOptions(cloud_topic=source.cloud_topic)
        return open_drive("rosbag-clouds", source.rosbag, clouds), source.rosbag, None
    drive = _bag_drive(source, source.pose_topic, source.tf_frame)
    truth = None
    if source.truth_topic is not None:
        try:
            truth = _truth_at(source, drive.timestamps)
        except BaseException:
            drive.close()
            raise
    return drive, source.rosbag, truth


def _bag_drive(source: SourceConfig, pose_topic: str | None, tf_frame: str | None) -> Any:
    assert source.rosbag is not None
    return bag_options.open_drive(
        source.rosbag, source.cloud_topic, pose_topic, tf_frame, origin_ne=source.origin_ne,
        yaw_deg=source.yaw_deg, max_pose_gap=source.max_pose_gap,
    )  # fmt: skip


def _truth_at(source: SourceConfig, stamps: Any) -> Any:
    """float64 [T, 4, 4] of ``--truth-topic`` at each of the drive's ``stamps`` (NaN where the
    topic has no pose for that scan)."""
    import numpy as np

    truth = _bag_drive(source, source.truth_topic, None)
    try:
        by_stamp = {int(t): p for t, p in zip(truth.timestamps, truth.poses, strict=True)}
    finally:
        truth.close()
    out = np.full((len(stamps), 4, 4), np.nan)
    for k, t in enumerate(stamps):
        pose = by_stamp.get(int(t))
        if pose is not None:
            out[k] = pose
    return out
