"""`pnvlad data prepare`: a recorded drive -> one benchmark run of submaps (see cli/data.py).

Parsing only: the options are declared below (so the command's signature stays one screen),
the drive is opened by :mod:`pnvlad_service.data.sources.registry` and the run is a
:class:`pnvlad_service.data.prepare_request.PrepareRequest`; library imports happen inside the
command so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path

import typer

from pnvlad_cli import rosbag as bag_options
from pnvlad_cli.common import progress_option, user_errors

_INPUT = "Input drive"
_GEOMETRY = "Submaps"
_SPEED = "Speed"
_OUTPUT = "Output"

_KITTI = typer.Option(
    None,
    "--kitti",
    help="KITTI-odometry sequence folder: velodyne/*.bin, poses.txt, optional times.txt "
    "and calib.txt.",
    rich_help_panel=_INPUT,
)
_SCANS = typer.Option(
    None,
    "--scans",
    help="Folder of scans named TIMESTAMP.EXT (µs), used with --poses CSV.",
    rich_help_panel=_INPUT,
)
_POSES = typer.Option(
    None,
    "--poses",
    help="With --scans: pose CSV (timestamp,northing,easting,yaw_deg|heading_deg[,height] or "
    "timestamp,r00..r23). With --kitti: a poses file other than <SEQ>/poses.txt.",
    rich_help_panel=_INPUT,
)
_READER = typer.Option(
    None,
    "--reader",
    help="Scan format for --scans when the suffix is ambiguous (kitti, nuscenes, nclt, "
    "benchmark, ...).",
    rich_help_panel=_INPUT,
)
_SKIP_MISSING = typer.Option(
    False,
    "--skip-missing",
    help="With --scans: drop CSV rows without a scan file and files without a row "
    "(default: refuse).",
    rich_help_panel=_INPUT,
)
_ORIGIN = typer.Option(
    None,
    "--origin",
    help="With --kitti: UTM NORTHING,EASTING of the first scan; with --rosbag: of the pose "
    "frame's origin (default 0,0: local metres).",
    rich_help_panel=_INPUT,
)
_UTM_ZONE = typer.Option(
    None,
    "--utm-zone",
    help="UTM zone of the poses' coordinates: number and latitude band (30U, 32N, 17S) or "
    "hemisphere (17 south). Recorded with the run; the index and its answers carry it "
    "(default: unknown). Give every run of a map the same.",
    rich_help_panel=_INPUT,
)
_YAW = typer.Option(
    0.0,
    "--yaw",
    help="With --kitti: direction the car faces at the first scan; with --rosbag: direction of "
    "the pose frame's x axis; degrees counter-clockwise from east (0 = east, 90 = north).",
    rich_help_panel=_INPUT,
)
_OUT = typer.Option(
    None,
    "--out",
    "-o",
    help="Run folder to write, e.g. benchmark_datasets/oxford/2024-05-01-10-00-00.",
    rich_help_panel=_OUTPUT,
)
_LAYOUT = typer.Option(
    "oxford",
    "--layout",
    help="oxford (20 m windows; train every 10 m, test every 20 m) or inhouse (25 m boxes; "
    "train every 10 m, test every 25 m).",
    rich_help_panel=_GEOMETRY,
)
_KIND = typer.Option(
    "both",
    "--kind",
    help="train, test, keyframe, a comma list of them, both (train,test) or all "
    "(train,test,keyframe); every kind in one pass, each scan read once. keyframe: one scan "
    "every --keyframe-stride metres, whole, through G with a --scan-range crop: the map for "
    "single-scan queries.",
    rich_help_panel=_GEOMETRY,
)
_KEYFRAME_STRIDE = typer.Option(
    None,
    "--keyframe-stride",
    help="Metres travelled between keyframes (default 5).",
    rich_help_panel=_GEOMETRY,
)
_SCAN_RANGE = typer.Option(
    None,
    "--scan-range",
    help="Metres from the sensor a keyframe keeps (default 50): single-scan queries to its "
    "map are cropped alike.",
    rich_help_panel=_GEOMETRY,
)
_RAW_SCANS = typer.Option(
    False,
    "--raw-scans",
    help="Also keep the raw scan at each test submap (OUT/raw_scans/, KITTI .bin, with its "
    "poses in raw_scans.csv): single-scan queries for pnvlad eval --queries scans.",
    rich_help_panel=_GEOMETRY,
)
_WINDOW = typer.Option(
    None,
    "--window",
    help="Metres of trajectory accumulated per submap, centred on it (default: the "
    "layout's, 20 oxford, 25 inhouse).",
    rich_help_panel=_GEOMETRY,
)
_BOX = typer.Option(
    None,
    "--box",
    help="Crop to a square box around the submap, UTM-aligned: 25 or 25x25 metres "
    "(default: none for oxford, 25 for inhouse; 0 = no crop).",
    rich_help_panel=_GEOMETRY,
)
_STRIDE = typer.Option(
    None,
    "--stride",
    help="Metres travelled between submaps of the train kind, or of the only kind asked "
    "for (default: the layout's).",
    rich_help_panel=_GEOMETRY,
)
_TEST_STRIDE = typer.Option(
    None,
    "--test-stride",
    help="With --kind both: metres between test submaps (default: the layout's, 20 or 25).",
    rich_help_panel=_GEOMETRY,
)
_G_CONFIG = typer.Option(
    None,
    "--g-config",
    help="YAML or JSON file of filter G settings (GConfig fields; default: the paper's).",
    rich_help_panel=_GEOMETRY,
)
_SEED = typer.Option(
    0,
    "--seed",
    help="Random seed; submap k uses seed + its centre scan index.",
    rich_help_panel=_GEOMETRY,
)
_POINTS_PER_SCAN = typer.Option(
    10_000,
    "--points-per-scan",
    help="Random subset of each scan accumulated (0 = every point).",
    rich_help_panel=_SPEED,
)
_MAX_RANGE = typer.Option(
    None,
    "--max-range",
    help="Drop points farther than this from the sensor, metres (default: keep all).",
    rich_help_panel=_SPEED,
)
_SCAN_STEP = typer.Option(
    1, "--scan-step", help="Use every k-th scan of each window.", rich_help_panel=_SPEED
)
_MIN_SPACING = typer.Option(
    0.05,
    "--min-spacing",
    help="Skip scans less than this many metres of travel after the last one used "
    "(a stop at a light adds one scan; 0 = use all).",
    rich_help_panel=_SPEED,
)
_RESUME = typer.Option(
    False,
    "--resume",
    help="Finish an interrupted run: keep submaps already written (same options needed).",
    rich_help_panel=_OUTPUT,
)
_OVERWRITE = typer.Option(
    False,
    "--overwrite",
    help="Delete the submaps the output folders hold and start again.",
    rich_help_panel=_OUTPUT,
)


def _parse_origin(text: str) -> tuple[float, float]:
    """'NORTHING,EASTING' -> (northing, easting) metres."""
    from pnvlad_service.errors import InputError

    parts = text.split(",")
    try:
        north, east = (float(p) for p in parts)
    except ValueError:
        raise InputError(
            f"expected NORTHING,EASTING in metres (e.g. 5735712.8,620084.4), got {text!r}",
            "--origin",
        ) from None
    return north, east


def _parse_box(text: str) -> float:
    """'25' or '25x25' -> 25.0 (a square box side, metres; 0 disables the crop)."""
    from pnvlad_service.errors import InputError

    parts = text.lower().split("x")
    try:
        sides = [float(p) for p in parts]
    except ValueError:
        sides = []
    if len(sides) not in (1, 2) or len(set(sides)) != 1 or not sides[0] >= 0:
        raise InputError(
            f"expected a square box side like 25 or 25x25 (metres), got {text!r}", "--box"
        )
    return sides[0]


def prepare(
    kitti: Path = _KITTI,
    scans: Path = _SCANS,
    poses: Path = _POSES,
    reader: str = _READER,
    skip_missing: bool = _SKIP_MISSING,
    origin: str = _ORIGIN,
    yaw: float = _YAW,
    utm_zone: str = _UTM_ZONE,
    rosbag: Path = bag_options.ROSBAG,
    cloud_topic: str = bag_options.CLOUD_TOPIC,
    pose_topic: str = bag_options.POSE_TOPIC,
    tf_frame: str = bag_options.TF_FRAME,
    max_pose_gap: float = bag_options.MAX_POSE_GAP,
    fix_topic: str = bag_options.FIX_TOPIC,
    odometry: str = bag_options.ODOMETRY,
    list_topics: bool = bag_options.LIST,
    out: Path = _OUT,
    layout: str = _LAYOUT,
    kind: str = _KIND,
    keyframe_stride: float = _KEYFRAME_STRIDE,
    scan_range: float = _SCAN_RANGE,
    raw_scans: bool = _RAW_SCANS,
    window: float = _WINDOW,
    box: str = _BOX,
    stride: float = _STRIDE,
    test_stride: float = _TEST_STRIDE,
    g_config: Path = _G_CONFIG,
    seed: int = _SEED,
    points_per_scan: int = _POINTS_PER_SCAN,
    max_range: float = _MAX_RANGE,
    scan_step: int = _SCAN_STEP,
    min_spacing: float = _MIN_SPACING,
    resume: bool = _RESUME,
    overwrite: bool = _OVERWRITE,
    progress: bool = progress_option(),
) -> None:
    """Cut a recorded drive into benchmark submaps (filter G) with their locations CSV.

    Scans are accumulated in the UTM frame over a window of trajectory centred on each submap,
    one submap every STRIDE metres travelled; each is filtered by G to 4096 points and written
    as OUT/FOLDER/TIMESTAMP.bin (98,304 bytes), the timestamp and position being those of
    the scan at the window's centre. The CSVs are written last; an interrupted run keeps only
    whole submaps, and --resume finishes it. See docs/PREPARE.md.

    Examples:

      pnvlad data prepare --kitti dataset/sequences/00 --origin 5735712.8,620084.4
      --utm-zone 30U --out bench/kitti/00

      pnvlad data prepare --scans drive/scans --poses drive/poses.csv --layout inhouse
      --out bench/campus/run1

      pnvlad data prepare --rosbag drive.bag --list

      pnvlad data prepare --rosbag drive.bag --cloud-topic /points --pose-topic /odom
      --origin 5735712.8,620084.4 --out bench/city/run1

      pnvlad data prepare --rosbag drive.bag --cloud-topic /points --fix-topic /fix
      --odometry kiss-icp --utm-zone 32U --kind all --out bench/city/run2   (fixes only)
    """
    with user_errors():
        from pnvlad_service.data.prepare_request import PrepareRequest, report_lines
        from pnvlad_service.data.sources.registry import DriveOptions, chosen, close_drive
        from pnvlad_service.errors import InputError

        if list_topics:
            if rosbag is None:
                raise InputError("applies to --rosbag only", "--list")
            bag_options.print_topics(rosbag)
            return
        source, path = chosen({"kitti": kitti, "csv": scans, "rosbag": rosbag})
        request = PrepareRequest.checked(
            out,
            kind=kind,
            stride=stride,
            test_stride=test_stride,
            keyframe_stride=keyframe_stride,
            scan_range=scan_range,
            g_config=g_config,
            resume=resume,
            overwrite=overwrite,
            layout=layout,
            window_m=window,
            box_m=None if box is None else _parse_box(box),
            seed=seed,
            max_points_per_scan=points_per_scan or None,
            max_range_m=max_range,
            scan_step=scan_step,
            min_scan_spacing_m=min_spacing,
            raw_scans=raw_scans,
            utm_zone=utm_zone,
        )
        options = DriveOptions(
            poses=poses, reader=reader, skip_missing=skip_missing,
            origin_ne=None if origin is None else _parse_origin(origin), yaw_deg=yaw,
            cloud_topic=cloud_topic, pose_topic=pose_topic, tf_frame=tf_frame,
            max_pose_gap=max_pose_gap, fix_topic=fix_topic, odometry=odometry, utm_zone=utm_zone,
        )  # fmt: skip
        drive = source.open(path, options)
        for note in source.notes(options):
            typer.secho(f"note: {note}", err=True, fg=typer.colors.YELLOW)
        try:
            result = request.run(drive, progress=progress)
        finally:
            close_drive(drive)
    for line in report_lines(result, len(drive)):
        typer.echo(line)
    line = source.report(drive)
    if line is not None:
        typer.echo(line)


def register(app: typer.Typer) -> None:
    """Add this module's commands to the `pnvlad data` group."""
    app.command("prepare")(prepare)
