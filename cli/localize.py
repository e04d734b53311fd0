"""`pnvlad localize`: where was this scan taken, or where was this drive, scan by scan?

Three modes, said by ``--mode`` or told by the arguments (a SCAN file; ``--rosbag`` /
``--kitti``, with ``--follow`` / ``--per-scan``): ``scan`` (one file, asked of a server or a
bundle in this process: a table or the JSON answer), ``follow`` and ``per-scan`` (a drive,
cli/replay.py). The command parses its options and calls the library;
library imports happen inside the functions so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli import replay as replay_options
from pnvlad_cli import rosbag as bag_options
from pnvlad_cli.common import model_option, progress_option, user_errors

log = logging.getLogger("pnvlad.localize")

#: ``--mode``'s values.
MODES = ("scan", "follow", "per-scan")

# How a single scan is verified (the options of `localize` that a drive does not take).
VERIFY = typer.Option(
    None,
    "--verify/--no-verify",
    help="Register the top candidates and re-rank them (default: when the bundle carries "
    "geometry; --verify with a bundle without it exits 2).",
)
SCALE = typer.Option(
    None,
    "--scale",
    help="Metres per unit of a preprocessed submap (its frame sidecar's scale), for a "
    "metric pose; estimated from the candidates when not given.",
)
RERANK = typer.Option(None, "--rerank", help="With --index: candidates to verify (default 10).")
VERIFY_THRESHOLD = typer.Option(
    None,
    "--verify-threshold",
    min=0.0,
    max=1.0,
    help="With --index: the confidence (0-1) a best match needs to be verified (default: "
    "the model's MODEL/verification.json, else 0.09; docs/VERIFY.md).",
)
VERIFY_STOP_SCORE = typer.Option(
    None,
    "--verify-stop-score",
    min=0.0,
    max=1.0,
    help="With --index: candidates are registered in retrieval order until one scores this "
    "within 25 m (default 0.25; 0.45 for push-broom maps such as Oxford RobotCar's, "
    "docs/VERIFY.md; 1 registers all).",
)


def format_matches(answer: dict[str, Any]) -> str:
    """The table `pnvlad localize` prints: rank, submap, run, northing, easting, distance,
    the verification score; then the verdict and the pose, and the stage times."""
    header = ("rank", "submap", "run", "northing", "easting", "distance", "score")
    rows = [
        (
            str(m["rank"]),
            str(m["timestamp"]),
            m["run"],
            f"{m['northing']:.2f}",
            f"{m['easting']:.2f}",
            "-" if m["distance"] is None else f"{m['distance']:.4f}",
            "-" if m.get("score") is None else f"{m['score']:.3f}",
        )
        for m in answer["matches"]
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    right = {0, 3, 4, 5, 6}

    def line(r: tuple[str, ...]) -> str:
        return "  ".join(
            c.rjust(w) if i in right else c.ljust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        ).rstrip()

    t = answer.get("timings_ms", {})
    footer = (
        f"preprocess {t.get('preprocess', 0):.1f} ms, embed {t.get('embed', 0):.1f} ms, "
        f"search {t.get('search', 0):.2f} ms, verify {t.get('verify', 0):.1f} ms, "
        f"total {t.get('total', 0):.1f} ms"
    )
    return "\n".join([line(header), *(line(r) for r in rows), verdict(answer), footer])


def verdict(answer: dict[str, Any]) -> str:
    """One line: verified or not (and why), and the pose of a verified answer."""
    v = answer.get("verification")
    if answer.get("verified") is None or v is None:
        return "not verified: verification off (or the index carries no geometry)"
    if not answer["verified"]:
        why = v.get("reason") or (
            f"confidence {v['confidence']:.3f} < {v['threshold']:.3f} "
            f"(best score {v['best_score']:.3f})"
        )
        return f"not verified: {why}"
    p = answer["pose"]
    return (
        f"verified (confidence {v['confidence']:.3f} >= {v['threshold']:.3f}, "
        f"score {p['fitness']:.3f}): "
        f"northing {p['northing']:.2f}, easting {p['easting']:.2f}, height {p['height']:.2f}, "
        f"yaw {p['yaw_deg']:.2f} deg ({p['frame']} frame, scale {p['scale']})"
    )


def _localize_here(
    index: Path,
    model: Path | None,
    points: Any,
    preprocess: bool,
    top_n: int,
    check: dict[str, Any],
) -> dict[str, Any]:
    """Search the bundle in this process: the same answer as the server's. ``check``:
    ``verify``, ``scale``, ``rerank``, ``threshold`` and ``stop_score`` as the command line
    gave them."""
    from pnvlad_service.localization.query.config import LocalizerConfig, VerifySection
    from pnvlad_service.localization.query.limits import Limits
    from pnvlad_service.localization.query.localizer import Localizer

    top_n = max(top_n, 1)
    # A local query is bounded by the bundle, not by the server's request limits.
    limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)), max_top_n=top_n)
    given = {"candidates": check["rerank"], "threshold": check["threshold"],
             "stop_score": check["stop_score"]}  # fmt: skip
    verify = VerifySection(**{k: v for k, v in given.items() if v is not None})
    with Localizer.load(index, model, LocalizerConfig(verify=verify)) as loc:
        answer = loc.localize(
            points,
            preprocess=preprocess,
            top_n=top_n,
            limits=limits,
            verify=check["verify"],
            scale=check["scale"],
        )
        return {**answer.to_json(), **loc.info.to_json()}


def _check_scan_only(threshold: float | None, stop_score: float | None) -> None:
    """:class:`InputError` for a single scan's verification setting given to a drive."""
    from pnvlad_service.errors import InputError

    for value, flag in ((threshold, "--verify-threshold"), (stop_score, "--verify-stop-score")):
        if value is not None:
            raise InputError("applies to a single scan (a drive registers near its prior)", flag)


def localize(
    scan: Path = typer.Argument(
        None, help="Point-cloud file (.bin submap, KITTI .bin, .npy, .pcd...); not with --rosbag."
    ),
    mode: str = typer.Option(
        None,
        "--mode",
        help="What to localise: 'scan' (the SCAN file), 'follow' (a drive, --rosbag or --kitti, "
        "tracked scan by scan) or 'per-scan' (every Nth scan of a drive asked alone). Default: "
        "scan with a SCAN file; follow with --rosbag or --kitti, per-scan with --per-scan.",
        show_default=False,
    ),
    url: str = typer.Option(None, "--url", "-u", help="Server to ask, e.g. http://127.0.0.1:8000."),
    index: Path = typer.Option(
        None, "--index", "-i", help="Search this bundle locally instead of a server."
    ),
    model: Path = model_option(help="With --index: the model (default: the bundle's)."),
    reader: str = typer.Option(
        None, "--reader", help="File format (benchmark, kitti, nuscenes, nclt, npy, pcd, ...)."
    ),
    preprocess: bool = typer.Option(
        False, "--preprocess", help="The scan is raw: run the filter G (as the map was) first."
    ),
    top_n: int = typer.Option(5, "--top-n", "-n", help="Matches to print."),
    verify: bool = VERIFY,
    scale: float = SCALE,
    rerank: int = RERANK,
    verify_threshold: float = VERIFY_THRESHOLD,
    verify_stop_score: float = VERIFY_STOP_SCORE,
    as_json: bool = typer.Option(False, "--json", help="Print the whole answer as JSON."),
    api_key: str = typer.Option(
        None, "--api-key", envvar="PNVLAD_API_KEY", help="Bearer token of the server."
    ),
    rosbag: Path = bag_options.ROSBAG,
    kitti: Path = replay_options.KITTI,
    cloud_topic: str = bag_options.CLOUD_TOPIC,
    pose_topic: str = bag_options.POSE_TOPIC,
    tf_frame: str = bag_options.TF_FRAME,
    truth_topic: str = replay_options.TRUTH_TOPIC,
    max_pose_gap: float = bag_options.MAX_POSE_GAP,
    origin: str = replay_options.ORIGIN,
    yaw: float = replay_options.YAW,
    follow: bool = replay_options.FOLLOW,
    odometry: str = replay_options.ODOMETRY,
    window: float = replay_options.WINDOW,
    radius: float = replay_options.RADIUS,
    confirm: int = replay_options.CONFIRM,
    failures: int = replay_options.FAILURES,
    fuse: bool | None = replay_options.FUSE,
    aligned_map: bool | None = replay_options.ALIGNED_MAP,
    every: int = replay_options.EVERY,
    out: Path = replay_options.OUT,
    map_bundle: Path = replay_options.MAP,
    plot: bool = replay_options.PLOT,
    foxglove: str = replay_options.FOXGLOVE,
    mcap: Path = replay_options.MCAP,
    ros2_bag: Path = replay_options.ROS2_BAG,
    trajectories: Path = replay_options.TRAJECTORIES,
    utm_zone: str = replay_options.UTM_ZONE,
    progress: bool = progress_option(),
) -> None:
    """Where was this scan taken? Print the nearest map places (UTM metres) as a table.

    Asks a running `pnvlad serve` (--url) or searches a bundle locally (--index). A benchmark
    submap (4096 points in [-1, 1]) goes as it is; a raw sensor scan needs --preprocess.
    When the bundle carries geometry the top candidates are registered to the scan and
    re-ranked: the table gives each one's score, then whether the best is verified and the
    scan's pose on the map (for a raw scan, the sensor's).

    With --rosbag (or --kitti, a KITTI sequence folder), follows a drive instead: every scan of
    --cloud-topic goes to a drive localiser that searches until a fix agrees with the odometry
    (--pose-topic / --tf, else KISS-ICP), then tracks it by registering each scan near the
    predicted pose, and says when it is lost; OUT.csv gets each scan's state, pose and (with
    --truth-topic, or the poses) its error, OUT.png the track coloured by state beside the
    truth, and a summary line the time to the first fix, the share verified, the errors and
    the speed. --per-scan asks with every Nth scan alone instead.

    --foxglove streams a drive live to the Foxglove app, --mcap writes the same to a file,
    --ros2-bag a ROS 2 bag, --trajectories TUM and KITTI files for evo (docs/TRACKING.md); one
    that fails is an error line, the drive and its CSV go on, the command exits 2.

    --mode says which of the three it is (scan, follow or per-scan); without it, the SCAN file,
    --rosbag / --kitti and --follow / --per-scan tell.

    Examples:

      pnvlad localize oxford/RUN/pointcloud_20m/TIMESTAMP.bin --url http://127.0.0.1:8000

      pnvlad localize scan.bin --reader kitti --preprocess --index map.index --json

      pnvlad localize --rosbag drive.bag --cloud-topic /points --pose-topic /odom
      --truth-topic /ground_truth --origin 5735712.8,620084.4 --url http://127.0.0.1:8000
      --map map.index --out follow/drive

      pnvlad localize --kitti sequences/00 --index map.index --out follow/kitti00

      pnvlad localize --mode per-scan --rosbag drive.bag --cloud-topic /points --every 5
      --index map.index
    """
    from pnvlad_service.errors import InputError

    with user_errors():
        if (url is None) == (index is None):
            raise InputError("give exactly one of --url and --index", "--url")
        _check_drive_source(rosbag, kitti, scan, reader, preprocess, as_json)
        mode = resolve_mode(mode, rosbag, kitti, follow)
        if mode != "scan":
            _check_scan_only(verify_threshold, verify_stop_score)
            _check_drive_options(mode, kitti, window, cloud_topic, pose_topic, tf_frame,
                                 truth_topic, odometry, radius, confirm, failures,
                                 fuse)  # fmt: skip
            config = replay_options.drive_config(
                "tracked" if mode == "follow" else "per-scan",
                every=every, odometry=odometry, window_m=window,
                tracking={"radius_m": radius, "confirm": confirm, "failures": failures,
                          "fuse": fuse},
                source={"rosbag": rosbag, "kitti": kitti, "cloud_topic": cloud_topic,
                        "pose_topic": pose_topic, "tf_frame": tf_frame,
                        "truth_topic": truth_topic, "max_pose_gap": max_pose_gap,
                        "origin_ne": replay_options.parse_origin(origin), "yaw_deg": yaw},
                service={"url": url, "index": index, "model": model, "api_key": api_key,
                         "top_n": top_n, "aligned_map": aligned_map},
                output={"out": out, "map_bundle": map_bundle, "plot": plot, "progress": progress,
                        **replay_options.view_outputs(foxglove, mcap, ros2_bag, trajectories,
                                                      utm_zone)},
            )  # fmt: skip
            replay_options.run(config)
            return
        if window is not None:
            raise InputError("applies to --rosbag --per-scan only", "--window")
        _check_no_views(foxglove, mcap, ros2_bag, trajectories, utm_zone,
                        aligned_map is not None, yaw or None)  # fmt: skip
        bag_options.check_unused(
            None, cloud_topic=cloud_topic, pose_topic=pose_topic, tf_frame=tf_frame,
            max_pose_gap=max_pose_gap, origin=origin, every=every, out=out, map=map_bundle,
            truth_topic=truth_topic, radius=radius, confirm=confirm, failures=failures,
            fuse=fuse is not None,  # --no-fuse is given too
        )  # fmt: skip
        check = {"verify": verify, "scale": scale, "rerank": rerank,
                 "threshold": verify_threshold, "stop_score": verify_stop_score}  # fmt: skip
        answer = _localize_scan(scan, reader, url, index, model, api_key, preprocess, top_n, check)
    if as_json:
        json.dump(answer, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        typer.echo(format_matches(answer))


def _check_no_views(*values: object) -> None:
    """InputError naming the first drive-only option (a robotics output, --aligned-map, --yaw)
    given without a drive."""
    from pnvlad_service.errors import InputError

    flags = ("--foxglove", "--mcap", "--ros2-bag", "--trajectories", "--utm-zone",
             "--aligned-map", "--yaw")  # fmt: skip
    for flag, value in zip(flags, values, strict=True):
        if value not in (None, False):
            raise InputError("applies to a drive (--rosbag or --kitti)", flag)


def _check_drive_options(
    mode: str,
    kitti: Path | None,
    window: float | None,
    cloud_topic: str | None,
    pose_topic: str | None,
    tf_frame: str | None,
    truth_topic: str | None,
    odometry: str,
    radius: float | None,
    confirm: int | None,
    failures: int | None,
    fuse: bool | None = None,
) -> None:
    """InputError naming an option that does not go with the drive mode: --window when
    following, an option of following with --per-scan, a bag's topics with --kitti."""
    from pnvlad_service.errors import InputError

    if mode == "follow" and window is not None:
        raise InputError("goes with --per-scan (a drive followed asks scan by scan)", "--window")
    if mode == "per-scan":
        replay_options.check_per_scan(truth_topic, odometry, radius, confirm, failures, window,
                                      fuse)  # fmt: skip
    if kitti is not None:
        bag_options.check_unused(None, cloud_topic=cloud_topic, pose_topic=pose_topic,
                                 tf_frame=tf_frame)  # fmt: skip


def resolve_mode(
    mode: str | None, rosbag: Path | None, kitti: Path | None, follow: bool | None
) -> str:
    """``--mode``, or the mode the arguments tell without it (a drive is followed unless
    ``--per-scan``; a KITTI sequence is always followed); InputError naming the option that
    does not go with it."""
    from pnvlad_service.errors import InputError

    drive = rosbag is not None or kitti is not None
    if mode is None:
        if not drive:
            return "scan"
        return "per-scan" if follow is False and kitti is None else "follow"
    if mode not in MODES:
        raise InputError(f"must be scan, follow or per-scan, got {mode!r}", "--mode")
    if mode == "scan" and drive:
        raise InputError("--mode scan asks with a SCAN file, not a drive",
                         "--kitti" if kitti is not None else "--rosbag")  # fmt: skip
    if mode != "scan" and not drive:
        raise InputError(f"--mode {mode} needs a drive: --rosbag BAG or --kitti SEQUENCE",
                         "--mode")  # fmt: skip
    if follow is not None and follow != (mode == "follow"):
        raise InputError(f"contradicts --mode {mode}", "--follow" if follow else "--per-scan")
    return mode


def _check_drive_source(
    rosbag: Path | None,
    kitti: Path | None,
    scan: Path | None,
    reader: str | None,
    preprocess: bool,
    as_json: bool,
) -> None:
    """InputError for --rosbag with --kitti, or either with a scan file's options."""
    from pnvlad_service.errors import InputError

    if rosbag is not None and kitti is not None:
        raise InputError("give --rosbag or --kitti, not both", "--kitti")
    if (rosbag is not None or kitti is not None) and (
        scan is not None or reader is not None or preprocess or as_json
    ):
        raise InputError(
            "a scan file, --reader, --preprocess and --json do not go with --rosbag or "
            "--kitti (their scans are raw: they are always preprocessed)",
            "--kitti" if kitti is not None else "--rosbag",
        )


def _localize_scan(
    scan: Path | None,
    reader: str | None,
    url: str | None,
    index: Path | None,
    model: Path | None,
    api_key: str | None,
    preprocess: bool,
    top_n: int,
    check: dict[str, Any],
) -> dict[str, Any]:
    """The answer for one scan file, from the server at ``url`` or the bundle at ``index``.
    ``check``: ``verify``, ``scale`` and ``rerank`` as the command line gave them."""
    from pnvlad_service.errors import InputError
    from pnvlad_service.io.readers import read_points, read_scan

    if scan is None:
        raise InputError("give a scan file (or --rosbag BAG to replay a bag)", "SCAN")
    if preprocess:  # a raw scan: its missing returns (points at the sensor) dropped and counted
        points, dropped = read_scan(scan, reader)
        if dropped:
            log.info("%s: %d missing returns (points at the sensor's origin) dropped", scan,
                     dropped)  # fmt: skip
    else:  # a preprocessed submap: its origin is a place like any other
        points = read_points(scan, reader)
    if url is None:
        assert index is not None
        return _localize_here(index, model, points, preprocess, top_n, check)
    from pnvlad_service.client import LocalizeClient

    for key, flag in (("rerank", "--rerank"), ("threshold", "--verify-threshold"),
                      ("stop_score", "--verify-stop-score")):  # fmt: skip
        if check[key] is not None:
            raise InputError(f"applies to --index; the server sets its own ({flag})", flag)
    with LocalizeClient(url, api_key=api_key) as client:
        return client.localize(
            points, top_n, preprocess, verify=check["verify"], scale=check["scale"]
        )
