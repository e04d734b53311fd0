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

from pnvlad_cli.common import user_errors


def serve(
    index: Path = typer.Option(
        None, "--index", "-i", help="Index bundle directory (pnvlad index build). Env PNVLAD_INDEX."
    ),
    checkpoint: Path = typer.Option(
        None,
        "--checkpoint",
        "-c",
        help="Model checkpoint directory; default: the one the bundle records. It must hold "
        "the weights the bundle was built with.",
    ),
    host: str = typer.Option(
        None, "--host", help="Interface to bind (default 127.0.0.1; 0.0.0.0 in a container)."
    ),
    port: int = typer.Option(None, "--port", "-p", help="TCP port (default 8000)."),
    workers: int = typer.Option(
        None, "--workers", "-w", help="Server processes, each with its own model (default 1)."
    ),
    torch_threads: int = typer.Option(None, "--torch-threads", help="torch intra-op threads."),
    batch_wait_ms: float = typer.Option(
        None, "--batch-wait-ms", help="Micro-batcher wait for requests being parsed (default 2)."
    ),
    log_level: str = typer.Option("info", "--log-level", help="uvicorn log level."),
) -> None:
    """Serve POST /localize over HTTP: a point cloud in, the nearest map places out.

    Loads the model and the index once. Refuses to start when the bundle was built with other
    weights than the checkpoint. Every setting can also come from the environment (PNVLAD_INDEX,
    PNVLAD_CHECKPOINT, PNVLAD_HOST, PNVLAD_PORT, PNVLAD_API_KEY for bearer-token auth,
    PNVLAD_MAX_BODY_BYTES, ...; see docs/SERVICE.md). OpenAPI docs at /docs.

    Example: pnvlad serve --index map.index --port 8000
    """
    options: dict[str, Any] = {
        "INDEX": index,
        "CHECKPOINT": checkpoint,
        "HOST": host,
        "PORT": port,
        "WORKERS": workers,
        "TORCH_THREADS": torch_threads,
        "BATCH_WAIT_MS": batch_wait_ms,
    }
    for name, value in options.items():
        if value is not None:
            os.environ[f"PNVLAD_{name}"] = str(
                Path(value).resolve() if isinstance(value, Path) else value
            )

    import uvicorn

    from pnvlad_service.server.service import check_compatible, resolve_checkpoint
    from pnvlad_service.server.settings import ServerSettings

    with user_errors():
        settings = ServerSettings()
        ckpt = resolve_checkpoint(settings)
        assert settings.index is not None
        check_compatible(settings.index, ckpt)
    os.environ["PNVLAD_CHECKPOINT"] = str(ckpt.resolve())
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
    """The table `pnvlad localize` prints: rank, submap, run, northing, easting, distance."""
    header = ("rank", "submap", "run", "northing", "easting", "distance")
    rows = [
        (
            str(m["rank"]),
            str(m["timestamp"]),
            m["run"],
            f"{m['northing']:.2f}",
            f"{m['easting']:.2f}",
            "-" if m["distance"] is None else f"{m['distance']:.4f}",
        )
        for m in answer["matches"]
    ]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    right = {0, 3, 4, 5}

    def line(r: tuple[str, ...]) -> str:
        return "  ".join(
            c.rjust(w) if i in right else c.ljust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        ).rstrip()

    t = answer.get("timings_ms", {})
    footer = (
        f"preprocess {t.get('preprocess', 0):.1f} ms, embed {t.get('embed', 0):.1f} ms, "
        f"search {t.get('search', 0):.2f} ms, total {t.get('total', 0):.1f} ms"
    )
    return "\n".join([line(header), *(line(r) for r in rows), footer])


def _post(url: str, points: Any, preprocess: bool, top_n: int, api_key: str | None) -> Any:
    import urllib.error
    import urllib.parse
    import urllib.request

    import numpy as np

    from pnvlad_service.errors import InputError

    arr = np.ascontiguousarray(points)
    dtype = "float64" if arr.dtype == np.float64 else "float32"
    arr = arr.astype("<f8" if dtype == "float64" else "<f4", copy=False)
    query = urllib.parse.urlencode(
        {"top_n": top_n, "preprocess": str(preprocess).lower(), "dtype": dtype}
    )
    headers = {"Content-Type": "application/octet-stream", "Accept": "application/json"}
    if api_key:
        headers["Authorization"] = f"Bearer {api_key}"
    req = urllib.request.Request(
        f"{url.rstrip('/')}/localize?{query}", data=arr.tobytes(), headers=headers, method="POST"
    )
    try:
        with urllib.request.urlopen(req, timeout=120) as resp:
            return json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        try:
            detail = json.loads(exc.read()).get("detail", exc.reason)
        except ValueError:
            detail = exc.reason
        raise InputError(f"server answered {exc.code}: {detail}", source=url) from None
    except urllib.error.URLError as exc:
        raise InputError(f"cannot reach the server: {exc.reason}", source=url) from None


def localize(
    scan: Path = typer.Argument(
        ..., help="Point-cloud file (.bin submap, KITTI .bin, .npy, .pcd...)."
    ),
    url: str = typer.Option(None, "--url", "-u", help="Server to ask, e.g. http://127.0.0.1:8000."),
    index: Path = typer.Option(
        None, "--index", "-i", help="Search this bundle locally instead of a server."
    ),
    checkpoint: Path = typer.Option(
        None, "--checkpoint", "-c", help="With --index: the model (default: the bundle's)."
    ),
    reader: str = typer.Option(
        None, "--reader", help="File format (benchmark, kitti, nuscenes, nclt, npy, pcd, ...)."
    ),
    preprocess: bool = typer.Option(
        False, "--preprocess", help="The scan is raw: run the filter G (as the map was) first."
    ),
    top_n: int = typer.Option(5, "--top-n", "-n", help="Matches to print."),
    as_json: bool = typer.Option(False, "--json", help="Print the whole answer as JSON."),
    api_key: str = typer.Option(
        None, "--api-key", envvar="PNVLAD_API_KEY", help="Bearer token of the server."
    ),
) -> None:
    """Where was this scan taken? Print the nearest map places (UTM metres) as a table.

    Asks a running `pnvlad serve` (--url) or searches a bundle locally (--index). A benchmark
    submap (4096 points in [-1, 1]) goes as it is; a raw sensor scan needs --preprocess.

    Examples:

      pnvlad localize oxford/RUN/pointcloud_20m/TIMESTAMP.bin --url http://127.0.0.1:8000

      pnvlad localize scan.bin --reader kitti --preprocess --index map.index --json
    """
    from pnvlad_service.errors import InputError
    from pnvlad_service.io.readers import read_points

    with user_errors():
        if (url is None) == (index is None):
            raise InputError("give exactly one of --url and --index", "--url")
        points = read_points(scan, reader)
        if url is not None:
            answer = _post(url, points, preprocess, top_n, api_key)
        else:
            from pnvlad_service.server.service import Localizer
            from pnvlad_service.server.settings import ServerSettings

            settings = ServerSettings(
                index=index, checkpoint=checkpoint, batch_wait_ms=0.0, max_top_n=max(top_n, 1)
            )
            loc = Localizer.load(settings)
            try:
                answer = loc.localize(points, preprocess, top_n)
            finally:
                loc.close()
    if as_json:
        json.dump(answer, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        typer.echo(format_matches(answer))
