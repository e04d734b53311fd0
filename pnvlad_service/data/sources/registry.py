"""The drive sources by name: what each one is, which options it reads, how it opens a drive.

Every kind of recording the library reads as a :class:`~pnvlad_service.data.drive.Drive` is one
:class:`DriveSource` in :data:`SOURCES` (``kitti``, ``csv``, ``rosbag``; and ``rosbag-clouds``,
a bag's clouds without poses, for a drive localised scan by scan), so a command picks a source
from a table instead of testing its options one by one. The options of every source are one
record, :class:`DriveOptions` (``None``, ``False`` or ``0`` when not given); a source reads the
ones it names in ``reads`` and refuses the others with a one-line :class:`InputError` (an
option only another source reads: "applies to --rosbag only", under the option's flag).

Example (a KITTI sequence placed in UTM, then a bag posed by its odometry)::

    from pnvlad_service.data.sources.registry import DriveOptions, close_drive, open_drive

    drive = open_drive("kitti", "dataset/sequences/00",
                       DriveOptions(origin_ne=(5735712.8, 620084.4)))
    bag = open_drive("rosbag", "drive.bag",
                     DriveOptions(cloud_topic="/points", pose_topic="/odom"))
    try:
        print(len(bag), bag.poses[0])
    finally:
        close_drive(bag)

A command that offers one option per source (``--kitti``, ``--scans``, ``--rosbag``) turns them
into a source with :func:`chosen`; :func:`register` adds a source (a new format is a module in
this package and one ``register(DriveSource(...))`` call here).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError

if TYPE_CHECKING:
    from pnvlad_service.data.drive import Drive

#: A bag's scans more than this many seconds from a pose sample are dropped (``max_pose_gap``).
DEFAULT_MAX_POSE_GAP_S = 2.0


def _flag(name: str) -> dict[str, str]:
    return {"flag": name}


@dataclass(frozen=True)
class DriveOptions:
    """The options of every source, each with its command-line flag (``None``, ``False`` or
    ``0.0``: not given).

    - ``poses``: a pose file (``csv``: the pose CSV, needed; ``kitti``: instead of
      ``<SEQ>/poses.txt``).
    - ``reader``, ``skip_missing``: the scan format of a ``csv`` drive's files, and whether rows
      without a file (and files without a row) are dropped rather than refused.
    - ``origin_ne`` (northing, easting, metres) and ``yaw_deg`` (counter-clockwise from east):
      where a ``kitti`` sequence's first scan, or a ``rosbag``'s pose frame, lies in UTM.
    - ``cloud_topic``, ``pose_topic`` / ``tf_frame``, ``max_pose_gap`` (seconds; ``None``: 2,
      ``0``: interpolate across any gap): a ``rosbag``'s clouds and poses.
    - ``fix_topic`` with ``odometry`` ``"kiss-icp"`` (instead of a pose topic or /tf): a
      ``rosbag`` with position fixes only (``sensor_msgs/NavSatFix``, turned into UTM in
      ``utm_zone``), posed by KISS-ICP laid onto them (:mod:`.rosbag_fixes`).
    """

    poses: Path | None = field(default=None, metadata=_flag("--poses"))
    reader: str | None = field(default=None, metadata=_flag("--reader"))
    skip_missing: bool = field(default=False, metadata=_flag("--skip-missing"))
    origin_ne: tuple[float, float] | None = field(default=None, metadata=_flag("--origin"))
    yaw_deg: float = field(default=0.0, metadata=_flag("--yaw"))
    cloud_topic: str | None = field(default=None, metadata=_flag("--cloud-topic"))
    pose_topic: str | None = field(default=None, metadata=_flag("--pose-topic"))
    tf_frame: str | None = field(default=None, metadata=_flag("--tf"))
    max_pose_gap: float | None = field(default=None, metadata=_flag("--max-pose-gap"))
    fix_topic: str | None = field(default=None, metadata=_flag("--fix-topic"))
    odometry: str | None = field(default=None, metadata=_flag("--odometry"))
    utm_zone: str | None = field(default=None, metadata=_flag("--utm-zone"))

    def given(self, name: str) -> bool:
        """Whether the option ``name`` was given (differs from its default)."""
        return getattr(self, name) not in (None, False, 0.0)


#: Option name -> its command-line flag.
FLAGS: dict[str, str] = {f.name: f.metadata["flag"] for f in fields(DriveOptions)}


@dataclass(frozen=True)
class DriveSource:
    """One kind of recording: ``name`` (the registry's key), ``flag`` (the command-line option
    that names its path), ``usage`` (that option with what goes with it, for messages),
    ``summary`` (one line), ``reads`` (the :class:`DriveOptions` it reads), ``own`` (those of
    ``reads`` that no other source takes: given with another source they are refused as
    "applies to FLAG only"), ``opener(path, options) -> Drive`` (checks the options it reads
    and refuses the others), ``notes(options)`` (lines worth telling a user once the drive is
    open) and ``report(drive)`` (one line on what the source read and dropped, or ``None``)."""

    name: str
    flag: str
    usage: str
    summary: str
    reads: tuple[str, ...]
    opener: Callable[[Path, DriveOptions], Drive]
    own: tuple[str, ...] = ()
    notes: Callable[[DriveOptions], list[str]] = lambda options: []
    report: Callable[[Any], str | None] = lambda drive: None

    def open(self, path: str | Path, options: DriveOptions | None = None) -> Drive:
        """The drive at ``path`` (see :func:`open_drive`)."""
        options = options or DriveOptions()
        for other in SOURCES.values():
            if other.name == self.name:
                continue
            for name in other.own:
                if options.given(name) and name not in self.reads:
                    raise InputError(f"applies to {other.flag} only", FLAGS[name])
        return self.opener(Path(path), options)


#: The sources, by name, in the order they are offered.
SOURCES: dict[str, DriveSource] = {}


def register(source: DriveSource) -> DriveSource:
    """Add ``source`` to :data:`SOURCES` (its name must be new); returns it."""
    if source.name in SOURCES:
        raise ValueError(f"a drive source named {source.name!r} is registered already")
    unknown = set(source.reads) - set(FLAGS)
    if unknown or not set(source.own) <= set(source.reads):
        raise ValueError(
            f"{source.name}: reads options DriveOptions lacks ({sorted(unknown)}) or owns some "
            "it does not read"
        )
    SOURCES[source.name] = source
    return source


def source_named(name: str) -> DriveSource:
    """The source registered as ``name``; :class:`InputError` listing the others."""
    try:
        return SOURCES[name]
    except KeyError:
        raise InputError(
            f"unknown drive source {name!r}; one of {sorted(SOURCES)}", "source"
        ) from None


def open_drive(name: str, path: str | Path, options: DriveOptions | None = None) -> Drive:
    """The drive at ``path`` read by the source ``name`` with ``options``; :class:`InputError`
    naming the option for one the source needs and lacks, or cannot use. A drive that holds a
    file open (a bag) is closed by :func:`close_drive`."""
    return source_named(name).open(path, options)


def close_drive(drive: object) -> None:
    """Close what ``drive`` holds open, if anything (a bag's reader)."""
    getattr(drive, "close", lambda: None)()


def chosen(paths: Mapping[str, Path | None]) -> tuple[DriveSource, Path]:
    """The one source given a path in ``paths`` (source name -> the path of its option, ``None``
    when not given), with that path; :class:`InputError` when none or several are given."""
    given = [(name, path) for name, path in paths.items() if path is not None]
    if len(given) != 1:
        usages = [source_named(name).usage for name in paths]
        listed = ", ".join(usages[:-1]) + f" or {usages[-1]}" if len(usages) > 1 else usages[0]
        raise InputError(f"give one of {listed}", source_named(next(iter(paths))).flag)
    name, path = given[0]
    return source_named(name), path


# --------------------------------------------------------------------------------------------
# The sources
# --------------------------------------------------------------------------------------------


def _open_kitti(path: Path, options: DriveOptions) -> Drive:
    from pnvlad_service.data.sources.kitti import KittiSequence

    if options.reader is not None or options.skip_missing:
        raise InputError("--reader and --skip-missing apply to --scans only", "--kitti")
    return KittiSequence(
        path,
        poses=options.poses,
        origin_ne=options.origin_ne or (0.0, 0.0),
        yaw_deg=options.yaw_deg,
    )


def _kitti_notes(options: DriveOptions) -> list[str]:
    if options.origin_ne is None:
        return ["no --origin given, positions are local metres from the first scan"]
    return []


def _open_csv(path: Path, options: DriveOptions) -> Drive:
    from pnvlad_service.data.sources.csv_drive import CsvDrive

    if options.poses is None:
        raise InputError("--scans needs --poses CSV", "--poses")
    if options.origin_ne is not None or options.yaw_deg != 0.0:
        raise InputError("--origin and --yaw apply to --kitti and --rosbag only", "--origin")
    return CsvDrive(path, options.poses, reader=options.reader, skip_missing=options.skip_missing)


def _open_fix_bag(path: Path, options: DriveOptions) -> Drive:
    """A bag posed by KISS-ICP laid onto its NavSatFix topic (``--fix-topic``)."""
    from pnvlad_service.data.sources.rosbag_fixes import open_fix_drive

    if options.odometry != "kiss-icp":
        raise InputError(
            "--fix-topic needs --odometry kiss-icp (the poses between and beside the fixes)",
            "--odometry",
        )
    if options.fix_topic is None:
        raise InputError(
            "--odometry kiss-icp goes with --fix-topic (a NavSatFix topic)", "--fix-topic"
        )
    if options.pose_topic is not None or options.tf_frame is not None:
        raise InputError("give --pose-topic/--tf or --fix-topic, not both", "--fix-topic")
    if options.origin_ne is not None or options.yaw_deg != 0.0:
        raise InputError("the fixes place the drive: --origin and --yaw do not apply", "--origin")
    return open_fix_drive(path, options.cloud_topic, options.fix_topic, options.utm_zone or "")


def _open_rosbag(path: Path, options: DriveOptions) -> Drive:
    from pnvlad_service.data.sources.rosbag import RosbagDrive

    if options.reader is not None or options.skip_missing or options.poses is not None:
        raise InputError(
            "--poses, --reader and --skip-missing do not apply to --rosbag", "--rosbag"
        )
    if options.cloud_topic is None:
        raise InputError(
            "--rosbag needs --cloud-topic (see the bag's topics with --list)", "--cloud-topic"
        )
    if options.fix_topic is not None or options.odometry is not None:
        return _open_fix_bag(path, options)
    if options.pose_topic is not None and options.tf_frame is not None:
        raise InputError("give --pose-topic or --tf, not both", "--tf")
    if options.pose_topic is None and options.tf_frame is None:
        raise InputError(
            "--rosbag needs --pose-topic TOPIC or --tf FRAME (see the bag's topics with --list)",
            "--pose-topic",
        )
    gap = options.max_pose_gap
    return RosbagDrive(
        path,
        options.cloud_topic,
        pose_topic=options.pose_topic,
        tf_frame=options.tf_frame,
        origin_ne=options.origin_ne or (0.0, 0.0),
        yaw_deg=options.yaw_deg,
        max_pose_gap_s=DEFAULT_MAX_POSE_GAP_S if gap is None else (gap or None),
    )


def _open_rosbag_clouds(path: Path, options: DriveOptions) -> Any:
    from pnvlad_service.data.sources.rosbag import RosbagClouds

    if options.cloud_topic is None:
        raise InputError(
            "--rosbag needs --cloud-topic (see the bag's topics with --list)", "--cloud-topic"
        )
    return RosbagClouds(path, options.cloud_topic)


def rosbag_report(drive: Any) -> str:
    """One line on a bag's drive: clouds read, scans kept, what was dropped and where the poses
    came from."""
    s = drive.stats
    line = f"{drive.bag.name}: {s.scans} of {s.clouds} clouds on {drive.cloud_topic} used"
    dropped = s.dropped()
    if dropped:
        line += f" (dropped: {dropped})"
    if s.nonfinite_points:
        line += f"; {s.nonfinite_points:,} NaN returns dropped from {s.scans_with_nonfinite} scans"
    zeros = drive.no_returns.line()
    if zeros:
        line += f"; {zeros}"
    return f"{line}; poses from {drive.pose_source}"


def no_returns_report(drive: Any) -> str | None:
    """The missing returns a drive of scan files dropped (points at the sensor's origin), or
    ``None``."""
    count = getattr(drive, "no_returns", None)
    return None if count is None else count.line()


#: The built-in sources: name, option, usage, summary, the options read, the opener.
for _source in (
    DriveSource(
        "kitti", "--kitti", "--kitti SEQ_DIR",
        "a KITTI-odometry sequence folder: velodyne/*.bin, poses.txt, times.txt, calib.txt",
        ("poses", "origin_ne", "yaw_deg"), _open_kitti, notes=_kitti_notes,
        report=no_returns_report,
    ),
    DriveSource(
        "csv", "--scans", "--scans DIR --poses CSV",
        "a folder of scans named TIMESTAMP.EXT with a CSV of their poses",
        ("poses", "reader", "skip_missing"), _open_csv, report=no_returns_report,
    ),
    DriveSource(
        "rosbag", "--rosbag", "--rosbag BAG",
        "a ROS 1 or ROS 2 bag: a PointCloud2 topic posed by a pose topic or /tf",
        ("origin_ne", "yaw_deg", "cloud_topic", "pose_topic", "tf_frame", "max_pose_gap",
         "fix_topic", "odometry", "utm_zone"),
        _open_rosbag,
        own=("cloud_topic", "pose_topic", "tf_frame", "max_pose_gap", "fix_topic", "odometry"),
        report=rosbag_report,
    ),
    # A bag's clouds alone, in time order (``RosbagClouds``: timestamps and scans, no poses):
    # what a drive localised scan by scan needs when the bag has no odometry; not a Drive that
    # `data prepare` can lay into submaps.
    DriveSource(
        "rosbag-clouds", "--rosbag", "--rosbag BAG --cloud-topic TOPIC",
        "a ROS 1 or ROS 2 bag's PointCloud2 topic without poses (localised scan by scan)",
        ("cloud_topic",), _open_rosbag_clouds,
    ),
):  # fmt: skip
    register(_source)
del _source
