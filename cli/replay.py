"""`pnvlad localize --rosbag` / `--kitti`: follow a drive against the service, a CSV and a PNG.

Called by `pnvlad localize` (cli/serve.py) when ``--rosbag`` or ``--kitti`` is given. By default
the drive is *followed* (:mod:`pnvlad_service.localization.follow`): every scan goes to a
:class:`~pnvlad_service.localization.tracking.DriveLocalizer` that searches until a fix is
confirmed, then tracks (a registration near the pose its odometry predicts), and says when it
is lost. With ``--per-scan`` every Nth scan is asked alone, as a raw-scan query
(:mod:`pnvlad_service.localization.replay`). The service is a server (``--url``) or a bundle
in this process (``--index``). Library imports happen inside the functions so that
`pnvlad --help` stays fast.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli import rosbag as bag_options

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
    True,
    "--follow/--per-scan",
    help="With --rosbag or --kitti: follow the drive (search until a fix is confirmed by the "
    "odometry, then track by registration near the prediction, say when lost; default), or "
    "ask with every Nth scan alone.",
    rich_help_panel=PANEL,
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
    "poses), 'kiss-icp' (LiDAR odometry on the scans, extra 'odometry') or 'none' (constant "
    "velocity); 'auto': poses when given, else kiss-icp when installed, else none.",
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


def check_per_scan(
    truth_topic: str | None,
    odometry: str,
    radius: float | None,
    confirm: int | None,
    failures: int | None,
    window: float | None = None,
) -> None:
    """InputError when an option of following is given with ``--per-scan`` (``--odometry
    kiss-icp`` goes with ``--window``)."""
    from pnvlad_service.errors import InputError

    if window is not None and not window > 0:
        raise InputError(f"must be a positive number of metres, got {window}", "--window")
    if window is not None and odometry not in ("auto", "poses", "kiss-icp"):
        raise InputError("a window is posed by the bag's poses or kiss-icp", "--odometry")
    given = {
        "--truth-topic": truth_topic,
        "--radius": radius,
        "--confirm": confirm,
        "--failures": failures,
        "--odometry": None if odometry == "auto" or window is not None else odometry,
    }
    for flag, value in given.items():  # fmt: skip
        if value is not None:
            raise InputError("applies to following a drive (not with --per-scan)", flag)


def parse_origin(text: str | None) -> tuple[float, float]:
    """``--origin`` NORTHING,EASTING -> (northing, easting); (0, 0) when not given."""
    if text is None:
        return (0.0, 0.0)
    from pnvlad_cli.data_prepare import _parse_origin

    return _parse_origin(text)


@contextmanager
def _service(
    url: str | None, index: Path | None, model: Path | None, api_key: str | None, top_n: int
) -> Iterator[Callable[[Any], dict[str, Any]]]:
    """``ask(points, kind="scan") -> answer`` for raw scans (or windows), from a server or
    from a local bundle."""
    if url is not None:
        from pnvlad_service.localization.client import LocalizeClient

        with LocalizeClient(url, api_key=api_key) as client:
            yield lambda points, kind="scan": client.localize(points, top_n, kind=kind)
        return
    from pnvlad_service.localization.query.limits import Limits
    from pnvlad_service.localization.query.localizer import Localizer

    assert index is not None
    with Localizer.load(index, model) as loc:

        def ask(points: Any, kind: str = "scan") -> dict[str, Any]:
            # A local query is bounded by the bundle, not by the server's request limits.
            limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
            return loc.localize(points, kind=kind, top_n=top_n, limits=limits).to_json()

        yield ask


def _map_positions(bundle: Path | None) -> Any:
    """float [M, 2] (northing, easting) of a bundle's submaps, or None."""
    if bundle is None:
        return None
    import numpy as np

    from pnvlad_service.index.bundle import METADATA_FILE, Metadata

    meta = Metadata.load(Path(bundle) / METADATA_FILE)
    return np.c_[meta.northing, meta.easting]


def _map_record(bundle: Path | None, url: str | None, api_key: str | None) -> Any:
    """The serving map's ``map`` entry (how its windows laid each scan): from the bundle's
    manifest, else from the server's ``GET /info``; None where neither says."""
    if bundle is not None:
        from pnvlad_service.index.manifest import Manifest

        return Manifest.read(bundle).map_record.to_json()
    if url is not None:
        from pnvlad_service.localization.client import LocalizeClient

        with LocalizeClient(url, api_key=api_key) as client:
            return client.info()["manifest"].get("map")
    return None


def replay_rosbag(
    *,
    rosbag: Path,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    origin_ne: tuple[float, float],
    yaw_deg: float,
    max_pose_gap: float | None,
    url: str | None,
    index: Path | None,
    model: Path | None,
    api_key: str | None,
    every: int | None,
    out: Path | None,
    map_bundle: Path | None,
    plot: bool,
    top_n: int = 5,
    progress: bool = True,
    window: float | None = None,
    odometry: str = "auto",
) -> None:
    """The whole replay: open the bag, ask, write OUT.csv and OUT.png, print the summary;
    with ``window``, each query the last ``window`` metres of the drive (:class:`Windows`)."""
    from pnvlad_service.data.sources.rosbag import RosbagClouds
    from pnvlad_service.errors import InputError
    from pnvlad_service.localization.replay import (
        Windows,
        plot_replay,
        replay,
        summarise,
        write_replay_csv,
    )

    every = 10 if every is None else every
    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "--every")
    if pose_topic is None and tf_frame is None:
        if cloud_topic is None:
            raise InputError("--rosbag needs --cloud-topic (see `pnvlad data prepare "
                             "--rosbag BAG --list`)", "--cloud-topic")  # fmt: skip
        drive: Any = RosbagClouds(rosbag, cloud_topic)
    else:
        drive = bag_options.open_drive(
            rosbag, cloud_topic, pose_topic, tf_frame, origin_ne=origin_ne, yaw_deg=yaw_deg,
            max_pose_gap=max_pose_gap,
        )  # fmt: skip
    if out is None:
        out = rosbag.with_name(f"{drive.name}.replay")
    try:
        map_ne = _map_positions(index if index is not None else map_bundle)
        windows = None
        if window is not None:
            posed = odometry == "kiss-icp" or (odometry == "auto" and pose_topic is None
                                               and tf_frame is None)  # fmt: skip
            map_record = _map_record(index if index is not None else map_bundle, url, api_key)
            windows = Windows(window, odometry=posed, map_record=map_record)
        with _service(url, index, model, api_key, top_n) as ask:
            rows = replay(drive, ask, every=every, progress=progress, window=windows)
    finally:
        drive.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    csv_path = write_replay_csv(rows, out.with_name(out.name + ".csv"))
    written = [str(csv_path)]
    if plot:
        poses = getattr(drive, "poses", None)
        png = plot_replay(
            rows,
            out.with_name(out.name + ".png"),
            map_ne=map_ne,
            trajectory_ne=None if poses is None else poses[:, [1, 0], 3],
            title=f"{drive.name}: {cloud_topic}, one scan in {every}"
            + ("" if window is None else f", the last {window:g} m a query"),
        )
        written.append(str(png))
    typer.echo(f"wrote {', '.join(written)}")
    typer.echo(summarise(rows).line())


@contextmanager
def _follow_service(
    url: str | None, index: Path | None, model: Path | None, api_key: str | None, top_n: int
) -> Iterator[Any]:
    """``ask(points, prior) -> answer`` (:data:`~pnvlad_service.localization.tracking.Ask`)
    from a server or from a local bundle."""
    from pnvlad_service.localization import tracking

    if url is not None:
        from pnvlad_service.localization.client import LocalizeClient

        with LocalizeClient(url, api_key=api_key) as client:
            yield tracking.http_ask(client, top_n)
        return
    from pnvlad_service.localization.query.localizer import Localizer

    assert index is not None
    with Localizer.load(index, model) as loc:
        yield tracking.local_ask(loc, top_n)


def _truth_at(
    rosbag: Path,
    cloud_topic: str,
    truth_topic: str,
    stamps: Any,
    origin_ne: tuple[float, float],
    yaw_deg: float,
    max_pose_gap: float | None,
) -> Any:
    """float64 [T, 4, 4] of ``truth_topic`` at each of the drive's ``stamps`` (NaN where the
    topic has no pose for that scan)."""
    import numpy as np

    truth = bag_options.open_drive(
        rosbag, cloud_topic, truth_topic, None, origin_ne=origin_ne, yaw_deg=yaw_deg,
        max_pose_gap=max_pose_gap,
    )  # fmt: skip
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


def _odometry_choice(choice: str, has_poses: bool) -> str:
    """``--odometry``: ``auto`` resolved (poses, else KISS-ICP when installed, else none)."""
    from pnvlad_service.errors import InputError

    if choice not in ("auto", "poses", "kiss-icp", "none"):
        raise InputError(f"must be auto, poses, kiss-icp or none, got {choice!r}", "--odometry")
    if choice == "poses" and not has_poses:
        raise InputError("the drive has no poses: give --pose-topic or --tf, or choose "
                         "kiss-icp or none", "--odometry")  # fmt: skip
    if choice != "auto":
        return choice
    if has_poses:
        return "poses"
    import importlib.util

    return "kiss-icp" if importlib.util.find_spec("kiss_icp") is not None else "none"


def follow(
    *,
    rosbag: Path | None,
    kitti: Path | None,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    truth_topic: str | None,
    origin_ne: tuple[float, float],
    yaw_deg: float,
    max_pose_gap: float | None,
    url: str | None,
    index: Path | None,
    model: Path | None,
    api_key: str | None,
    every: int | None,
    out: Path | None,
    map_bundle: Path | None,
    plot: bool,
    odometry: str = "auto",
    radius: float | None = None,
    confirm: int | None = None,
    failures: int | None = None,
    top_n: int = 5,
    progress: bool = True,
) -> None:
    """Follow a bag's or a KITTI sequence's drive: open it, follow it, write OUT.csv and
    OUT.png, print the summary line and the stages' times."""
    import time

    from pnvlad_service.errors import InputError
    from pnvlad_service.localization.follow import follow_drive

    every = 1 if every is None else every
    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "--every")
    config = _tracker_config(radius, confirm, failures)
    drive, source = _open_followed(
        rosbag, kitti, cloud_topic, pose_topic, tf_frame, truth_topic, origin_ne, yaw_deg,
        max_pose_gap,
    )  # fmt: skip
    try:
        poses = getattr(drive, "poses", None)
        how = _odometry_choice(odometry, poses is not None)
        truth = poses
        if truth_topic is not None:
            assert rosbag is not None and cloud_topic is not None
            truth = _truth_at(rosbag, cloud_topic, truth_topic, drive.timestamps, origin_ne,
                              yaw_deg, max_pose_gap)  # fmt: skip
        if out is None:
            out = source.with_name(f"{drive.name}.follow")
        bundle = index if index is not None else map_bundle
        positions, map_ne, known = _followed_map(bundle, truth is not None)
        with _follow_service(url, index, model, api_key, top_n) as ask:
            t0 = time.perf_counter()
            rows = follow_drive(
                drive, ask, every=every, odometry=how, truth=truth, config=config,  # type: ignore[arg-type]
                positions=positions, truth_of_map=known, progress=progress,
            )  # fmt: skip
            wall = time.perf_counter() - t0
    finally:
        close = getattr(drive, "close", None)
        if close is not None:
            close()
    _report_followed(rows, wall, out, how, plot=plot, map_ne=map_ne,
                     title=f"{drive.name}: every scan" if every == 1 else
                     f"{drive.name}: one scan in {every}")  # fmt: skip


def _tracker_config(radius: float | None, confirm: int | None, failures: int | None) -> Any:
    """The :class:`~pnvlad_service.localization.tracking.TrackerConfig` with ``--radius``,
    ``--confirm`` and ``--failures`` where given (InputError naming the flag it refuses)."""
    from dataclasses import replace

    from pnvlad_service.errors import InputError
    from pnvlad_service.localization.tracking import TrackerConfig

    config = TrackerConfig()
    for flag, name, value in (("--radius", "radius_m", radius), ("--confirm", "confirm", confirm),
                              ("--failures", "failures", failures)):  # fmt: skip
        if value is None:
            continue
        try:
            config = replace(config, **{name: value})
        except ValueError as exc:
            raise InputError(str(exc), flag) from None
    return config


def _open_followed(
    rosbag: Path | None,
    kitti: Path | None,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    truth_topic: str | None,
    origin_ne: tuple[float, float],
    yaw_deg: float,
    max_pose_gap: float | None,
) -> tuple[Any, Path]:
    """(the drive to follow, the file or folder it came from): the KITTI sequence, or the bag's
    clouds with the poses of ``pose_topic`` / ``tf_frame`` when given."""
    from pnvlad_service.errors import InputError

    if kitti is not None:
        from pnvlad_service.data.sources.kitti import KittiSequence

        if truth_topic is not None:
            raise InputError("applies to --rosbag only (a KITTI sequence's poses are its truth)",
                             "--truth-topic")  # fmt: skip
        return KittiSequence(kitti, origin_ne=origin_ne, yaw_deg=yaw_deg), kitti
    assert rosbag is not None
    if pose_topic is None and tf_frame is None:
        from pnvlad_service.data.sources.rosbag import RosbagClouds

        if cloud_topic is None:
            raise InputError("--rosbag needs --cloud-topic (see `pnvlad data prepare "
                             "--rosbag BAG --list`)", "--cloud-topic")  # fmt: skip
        return RosbagClouds(rosbag, cloud_topic), rosbag
    drive = bag_options.open_drive(
        rosbag, cloud_topic, pose_topic, tf_frame, origin_ne=origin_ne, yaw_deg=yaw_deg,
        max_pose_gap=max_pose_gap,
    )  # fmt: skip
    return drive, rosbag


def _followed_map(bundle: Path | None, with_truth: bool) -> tuple[Any, Any, Any]:
    """(the map's positions, float [M, 2] northing and easting of its entries, its own truth
    when the drive has truth) of the bundle at ``bundle``; ``None`` for each without one."""
    if bundle is None:
        return None, None, None
    import numpy as np

    from pnvlad_service.index.bundle import METADATA_FILE, Metadata
    from pnvlad_service.localization.follow import map_truth
    from pnvlad_service.localization.verify.prior import MapPositions

    meta = Metadata.load(Path(bundle) / METADATA_FILE)
    positions = MapPositions.of_metadata(meta)
    map_ne = np.c_[meta.northing, meta.easting]
    known = map_truth(bundle) if with_truth else None
    return positions, map_ne, known


def _report_followed(
    rows: Any, wall: float, out: Path, how: str, *, plot: bool, map_ne: Any, title: str
) -> None:
    """Write OUT.csv (and OUT.png), print the odometry, the stages' mean times and the
    summary line."""
    from pnvlad_service.localization.follow_report import (
        plot_follow,
        stage_means,
        summarise_follow,
        write_follow_csv,
    )

    out.parent.mkdir(parents=True, exist_ok=True)
    written = [str(write_follow_csv(rows, out.with_name(out.name + ".csv")))]
    if plot:
        png = plot_follow(rows, out.with_name(out.name + ".png"), map_ne=map_ne, title=title)
        written.append(str(png))
    typer.echo(f"wrote {', '.join(written)}")
    typer.echo(f"odometry: {how}")
    for mode, means in stage_means(rows).items():
        parts = ", ".join(f"{k} {v:.1f}" for k, v in means.items() if k != "scans")
        what = "searching" if mode == "search" else "tracking"
        typer.echo(f"stages, {what} ({int(means['scans'])} scans), mean ms: {parts}")
    typer.echo(summarise_follow(rows, wall).line())
