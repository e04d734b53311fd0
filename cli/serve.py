"""`pnvlad serve` (the HTTP service) and `pnvlad localize` (its client, or a local query).

Library imports happen inside the commands so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli import replay as replay_options
from pnvlad_cli import rosbag as bag_options
from pnvlad_cli.common import model_option, progress_option, user_errors


def serve(
    index: Path = typer.Option(
        None, "--index", "-i", help="Index bundle directory (pnvlad index build). Env PNVLAD_INDEX."
    ),
    model: Path = model_option(
        help="The model; default: the one the bundle records. It must hold the weights the "
        "bundle was built with. Env PNVLAD_CHECKPOINT."
    ),
    host: str = typer.Option(
        None, "--host", help="Interface to bind (default 127.0.0.1; 0.0.0.0 in a container)."
    ),
    port: int = typer.Option(None, "--port", "-p", help="TCP port (default 8000)."),
    workers: int = typer.Option(
        None, "--workers", "-w", help="Server processes, each with its own model (default 1)."
    ),
    runtime: str = typer.Option(
        None,
        "--runtime",
        help="What embeds: torch, onnx (ONNX Runtime on the model's model.onnx, pnvlad model "
        "export) or auto (default: torch when installed, else onnx). Env PNVLAD_RUNTIME.",
    ),
    threads: int = typer.Option(
        None, "--threads", help="Encoder threads (ONNX Runtime's or torch's). Env PNVLAD_THREADS."
    ),
    torch_threads: int = typer.Option(None, "--torch-threads", help="torch intra-op threads."),
    batch_wait_ms: float = typer.Option(
        None, "--batch-wait-ms", help="Micro-batcher wait for requests being parsed (default 2)."
    ),
    rerank: int = typer.Option(
        None,
        "--rerank",
        help="Candidates registered to each query and re-ranked, when the bundle carries "
        "geometry (default 10). A request turns it off with verify=false.",
    ),
    verify_threshold: float = typer.Option(
        None,
        "--verify-threshold",
        help="Confidence (0-1) a best match needs to be verified (default: the one chosen for "
        "the model on training-layout submaps, MODEL/verification.json from pnvlad eval "
        "--rerank K --save-threshold; else 0.09, docs/VERIFY.md).",
    ),
    verify_stop_score: float = typer.Option(
        None,
        "--verify-stop-score",
        help="Candidates are registered in retrieval order, one at a time, and the rest skipped "
        "once one scores this within the place radius (default 0.25; 1 registers all K).",
    ),
    verify_cache: int = typer.Option(
        None,
        "--verify-cache",
        help="Prepared candidate clouds kept in memory for later queries (default 128, about "
        "1 MB each; 0 keeps none).",
    ),
    log_level: str = typer.Option("info", "--log-level", help="uvicorn log level."),
) -> None:
    """Serve POST /localize over HTTP: a point cloud in, the nearest map places out.

    When the bundle carries geometry (built from a tree with frame sidecars), the top
    candidates are registered to the query and re-ranked, and each answer says whether its
    best match is verified and gives the query's pose on the map.

    Loads the model and the index once. Refuses to start when the bundle was built with other
    weights than the checkpoint, when its geometry file is truncated or fails its hash, or
    when the model.onnx it would run was exported from other weights. Embeds with ONNX Runtime
    when torch is not installed (or with --runtime onnx), and says which at start-up and in
    /readyz. POST /admin/reload (with PNVLAD_ADMIN_KEY or PNVLAD_API_KEY) or SIGHUP swaps in a
    new bundle while it serves; one that fails its checks is refused and the old one serves on.
    Every setting can also come from the environment (PNVLAD_INDEX, PNVLAD_CHECKPOINT,
    PNVLAD_HOST, PNVLAD_PORT, PNVLAD_API_KEY for bearer-token auth, PNVLAD_MAX_BODY_BYTES, ...;
    see docs/SERVICE.md). OpenAPI docs at /docs.

    Example: pnvlad serve --index map.index --port 8000
    """
    # Before torch loads its OpenMP runtime (libgomp reads this once): the encoder's threads
    # spin about 0.2 ms between the ~100 parallel regions of a forward pass instead of 300,000
    # iterations. The single cloud of an idle server keeps its speed, and under load the
    # spinning threads give the cores back to the cloud workers and the registration sooner
    # (docs/SERVICE.md, "How a request runs"). A value the user set is kept. The verification
    # child drops the one set here (the marker says so) and lets its threads sleep instead.
    from pnvlad_service.localization.verify.verify_process import SPINCOUNT_MARK  # no torch

    if "GOMP_SPINCOUNT" not in os.environ:
        os.environ["GOMP_SPINCOUNT"] = "20000"
        os.environ[SPINCOUNT_MARK] = "1"
    options: dict[str, Any] = {
        "INDEX": index,
        "CHECKPOINT": model,
        "HOST": host,
        "PORT": port,
        "WORKERS": workers,
        "RUNTIME": runtime,
        "THREADS": threads,
        "TORCH_THREADS": torch_threads,
        "BATCH_WAIT_MS": batch_wait_ms,
        "RERANK": rerank,
        "VERIFY_THRESHOLD": verify_threshold,
        "VERIFY_STOP_SCORE": verify_stop_score,
        "VERIFY_CACHE": verify_cache,
    }
    for name, value in options.items():
        if value is not None:
            os.environ[f"PNVLAD_{name}"] = str(
                Path(value).resolve() if isinstance(value, Path) else value
            )

    import uvicorn

    from pnvlad_service.errors import InputError
    from pnvlad_service.index.geometry import check_geometry
    from pnvlad_service.localization.query.localizer import checked_model
    from pnvlad_service.models.onnx_encoder import check_onnx_file
    from pnvlad_service.models.runtimes import choose_runtime
    from pnvlad_service.server.settings import ServerSettings

    with user_errors():
        settings = ServerSettings()
        if settings.index is None:
            raise InputError("no index bundle given (--index or PNVLAD_INDEX)", "index")
        identity = checked_model(settings.index, settings.checkpoint)
        check_geometry(settings.index, verify=settings.verify_bundle)
        if choose_runtime(identity.checkpoint, settings.runtime) == "onnx":
            check_onnx_file(identity.checkpoint, identity.weights_sha256)
    os.environ["PNVLAD_CHECKPOINT"] = identity.checkpoint
    uvicorn.run(
        "pnvlad_service.server.app:create_app_from_env",
        factory=True,
        host=settings.host,
        port=settings.port,
        workers=settings.workers,
        log_level=log_level,
        timeout_graceful_shutdown=10,
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
    ``verify``, ``scale`` and ``rerank`` as the command line gave them."""
    from pnvlad_service.localization.query.config import LocalizerConfig, VerifySection
    from pnvlad_service.localization.query.limits import Limits
    from pnvlad_service.localization.query.localizer import Localizer

    top_n = max(top_n, 1)
    # A local query is bounded by the bundle, not by the server's request limits.
    limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)), max_top_n=top_n)
    verify = (
        VerifySection() if check["rerank"] is None else VerifySection(candidates=check["rerank"])
    )
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


def localize(
    scan: Path = typer.Argument(
        None, help="Point-cloud file (.bin submap, KITTI .bin, .npy, .pcd...); not with --rosbag."
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
    verify: bool = typer.Option(
        None,
        "--verify/--no-verify",
        help="Register the top candidates and re-rank them (default: when the bundle carries "
        "geometry; --verify with a bundle without it exits 2).",
    ),
    scale: float = typer.Option(
        None,
        "--scale",
        help="Metres per unit of a preprocessed submap (its frame sidecar's scale), for a "
        "metric pose; estimated from the candidates when not given.",
    ),
    rerank: int = typer.Option(
        None, "--rerank", help="With --index: candidates to verify (default 10)."
    ),
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
    every: int = replay_options.EVERY,
    out: Path = replay_options.OUT,
    map_bundle: Path = replay_options.MAP,
    plot: bool = replay_options.PLOT,
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

    Examples:

      pnvlad localize oxford/RUN/pointcloud_20m/TIMESTAMP.bin --url http://127.0.0.1:8000

      pnvlad localize scan.bin --reader kitti --preprocess --index map.index --json

      pnvlad localize --rosbag drive.bag --cloud-topic /points --pose-topic /odom
      --truth-topic /ground_truth --origin 5735712.8,620084.4 --url http://127.0.0.1:8000
      --map map.index --out follow/drive

      pnvlad localize --kitti sequences/00 --index map.index --out follow/kitti00
    """
    from pnvlad_service.errors import InputError

    with user_errors():
        if (url is None) == (index is None):
            raise InputError("give exactly one of --url and --index", "--url")
        bag = {"cloud_topic": cloud_topic, "pose_topic": pose_topic, "tf_frame": tf_frame}
        bag |= {"max_pose_gap": max_pose_gap, "origin": origin, "every": every, "out": out}
        bag |= {"map": map_bundle, "truth_topic": truth_topic, "radius": radius}
        bag |= {"confirm": confirm, "failures": failures}
        _check_drive_source(rosbag, kitti, scan, reader, preprocess, as_json)
        # What following a drive and asking with every Nth scan of a bag both take.
        drive: dict[str, Any] = {
            "rosbag": rosbag, "cloud_topic": cloud_topic, "pose_topic": pose_topic,
            "tf_frame": tf_frame, "yaw_deg": yaw, "max_pose_gap": max_pose_gap, "url": url,
            "index": index, "model": model, "api_key": api_key, "every": every, "out": out,
            "map_bundle": map_bundle, "plot": plot, "top_n": top_n, "progress": progress,
        }  # fmt: skip
        if kitti is not None or (rosbag is not None and follow):
            if window is not None:
                raise InputError("goes with --per-scan (a drive followed asks scan by scan)",
                                 "--window")  # fmt: skip
            if kitti is not None:
                bag_options.check_unused(None, cloud_topic=cloud_topic, pose_topic=pose_topic,
                                         tf_frame=tf_frame)  # fmt: skip
            replay_options.follow(
                **drive,
                kitti=kitti,
                truth_topic=truth_topic,
                origin_ne=replay_options.parse_origin(origin),
                odometry=odometry,
                radius=radius,
                confirm=confirm,
                failures=failures,
            )
            return
        if rosbag is not None:
            replay_options.check_per_scan(truth_topic, odometry, radius, confirm, failures, window)
            replay_options.replay_rosbag(
                **drive,
                origin_ne=replay_options.parse_origin(origin),
                window=window,
                odometry=odometry,
            )
            return
        if window is not None:
            raise InputError("applies to --rosbag --per-scan only", "--window")
        bag_options.check_unused(None, **bag)
        if yaw != 0.0:
            raise InputError("applies to --rosbag only", "--yaw")
        check = {"verify": verify, "scale": scale, "rerank": rerank}
        answer = _localize_scan(scan, reader, url, index, model, api_key, preprocess, top_n, check)
    if as_json:
        json.dump(answer, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        typer.echo(format_matches(answer))


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
    from pnvlad_service.io.readers import read_points

    if scan is None:
        raise InputError("give a scan file (or --rosbag BAG to replay a bag)", "SCAN")
    points = read_points(scan, reader)
    if url is None:
        assert index is not None
        return _localize_here(index, model, points, preprocess, top_n, check)
    from pnvlad_service.localization.client import LocalizeClient

    if check["rerank"] is not None:
        raise InputError("applies to --index; the server sets its own (--rerank)", "--rerank")
    with LocalizeClient(url, api_key=api_key) as client:
        return client.localize(
            points, top_n, preprocess, verify=check["verify"], scale=check["scale"]
        )
