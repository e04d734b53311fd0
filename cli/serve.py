"""`pnvlad serve`: the HTTP service (its client on the command line: cli/localize.py).

Library imports happen inside the command so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import typer

from pnvlad_cli.common import model_option, user_errors


def _export(options: dict[str, Any]) -> None:
    """Each given option as its ``PNVLAD_*`` variable, the one place the server's settings are
    read from: paths made absolute; a ``pretrained:NAME`` is a name, not a path."""
    from pnvlad_service.models.pretrained import is_pretrained

    for name, value in options.items():
        if value is not None:
            as_path = isinstance(value, Path) and not is_pretrained(value)
            os.environ[f"PNVLAD_{name}"] = str(Path(value).resolve() if as_path else value)


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
        "once one scores this within the place radius (default 0.25; 0.45 for push-broom maps "
        "such as Oxford RobotCar's, docs/VERIFY.md; 1 registers all K).",
    ),
    verify_cache: int = typer.Option(
        None,
        "--verify-cache",
        help="Prepared candidate clouds kept in memory for later queries (default 128, about "
        "1 MB each; 0 keeps none).",
    ),
    log_level: str = typer.Option("info", "--log-level", help="uvicorn log level."),
    foxglove: str = typer.Option(
        None,
        "--foxglove",
        help="Stream each answered query live to Foxglove (ws://HOST:PORT): its candidates' "
        "positions and its verified pose on the map. HOST:PORT, or :PORT on 127.0.0.1; needs "
        "the 'view' extra; one worker.",
    ),
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
        "FOXGLOVE": foxglove,
    }
    _export(options)

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
        if settings.foxglove is not None:
            _check_foxglove(settings.foxglove, settings.workers)
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


def _check_foxglove(host_port: str, workers: int) -> None:
    """InputError naming ``--foxglove`` for a HOST:PORT that is not one, that cannot be bound
    now, or with more than one worker (each would bind it); the extra is checked too."""
    import socket

    from pnvlad_service.errors import InputError
    from pnvlad_service.extras import require
    from pnvlad_service.localization.outputs.foxglove_view import parse_host_port

    host, port = parse_host_port(host_port)
    if workers > 1:
        raise InputError("streams from one process: give --workers 1", "--foxglove")
    require("foxglove", "foxglove-sdk", "view", "the live view (--foxglove)")
    with socket.socket() as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise InputError(f"{host}:{port}: {exc.strerror or exc}", "--foxglove") from None
