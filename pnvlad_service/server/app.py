"""The FastAPI app: ``create_app(settings)``; ``create_app_from_env()`` for uvicorn's factory.

Routes (one router per resource, :mod:`pnvlad_service.server.routes`): ``POST /localize``
(JSON, raw float32/float64 xyz, or ``.npy``), ``POST /localize/batch``, ``GET /healthz``,
``GET /readyz``, ``GET /info``, ``GET /metrics``, ``POST /admin/reload`` and the API docs at
``/docs`` and ``/redoc`` (served from installed assets, :mod:`pnvlad_service.server.docs`).
Errors are ``application/problem+json``. Bodies are bounded while read
(:class:`~pnvlad_service.server.middleware.BodyLimit`). The lifespan loads the
:class:`~pnvlad_service.localization.query.localizer.Localizer` once, in the thread pool, and
puts it in a :class:`~pnvlad_service.localization.query.serving.ServingMap`, which swaps it for a
new bundle on ``POST /admin/reload`` or SIGHUP; the routes lease it, and get the settings and the
metrics, through :mod:`pnvlad_service.server.deps`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.concurrency import run_in_threadpool

from pnvlad_service import __version__
from pnvlad_service.errors import InputError, PnvladError
from pnvlad_service.localization.query.localizer import Localizer, QueryEncoder, set_threads
from pnvlad_service.localization.query.serving import ReloadInProgress, ServingMap
from pnvlad_service.server import docs, problems
from pnvlad_service.server.contract import Contract
from pnvlad_service.server.deps import require_key
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.middleware import BodyLimit, RequestCounter
from pnvlad_service.server.routes import admin, localize, ops
from pnvlad_service.server.settings import ServerSettings

log = logging.getLogger(__name__)

DESCRIPTION = (
    "LiDAR place recognition: send a point cloud, get the nearest places of the map "
    "(UTM northing/easting) with their descriptor distances."
)


def load_localizer(
    settings: ServerSettings,
    on_batch: Callable[[int], None] | None = None,
    index: Path | None = None,
    model: Path | None = None,
    encoder: QueryEncoder | None = None,
) -> Localizer:
    """The localiser that ``settings`` name (bundle, model, and the sections of its config:
    :meth:`ServerSettings.localizer_config`); ``index`` and ``model`` replace the settings'
    (a reload), ``encoder`` is reused when it holds the model's weights."""
    set_threads(settings.torch_threads or settings.threads, settings.faiss_threads)
    index = index or settings.index
    if index is None:
        raise InputError("no index bundle given (--index or PNVLAD_INDEX)", "index")
    return Localizer.load(
        index,
        model or settings.checkpoint,
        settings.localizer_config(),
        encoder=encoder,
        on_batch=on_batch,
    )


def reload_loader(
    settings: ServerSettings, on_batch: Callable[[int], None] | None
) -> Callable[[Path, Path, Any], Localizer]:
    """How a :class:`ServingMap` loads the next bundle: as at start-up, warmed up unless it
    reuses the serving encoder (which is warm)."""

    def load(index: Path, model: Path, encoder: Any) -> Localizer:
        loc = load_localizer(settings, on_batch, index, model, encoder)
        if loc.encoder is not encoder:
            try:
                loc.warm_up(min(settings.warm_up, settings.batch_max_size))
            except BaseException:
                loc.close()
                raise
        return loc

    return load


def reload_now(app: FastAPI) -> None:
    """SIGHUP: reload the serving bundle's path (a new bundle written there, e.g. by
    ``pnvlad index add``); a bundle that fails its checks is logged and the old one serves on."""
    serving: ServingMap | None = app.state.serving
    metrics = app.state.metrics
    if serving is None:
        return
    try:
        done = serving.reload()
    except ReloadInProgress:
        metrics.reloads.labels("busy").inc()
        log.warning("SIGHUP: a reload is already in progress")
        return
    except PnvladError as exc:
        metrics.reloads.labels("refused").inc()
        log.error(
            "SIGHUP: reload refused, still serving %s: %s", serving.current.info.index.id, exc
        )
        return
    metrics.reloads.labels("swapped").inc()
    log.info("SIGHUP: now serving %s (%.2f s)", done.current["index"]["id"], done.load_s)


@contextlib.contextmanager
def _sighup(app: FastAPI) -> Any:
    """SIGHUP reloads while the block runs (in the main thread's event loop only: uvicorn's
    process; under ``--workers N`` uvicorn's supervisor restarts the workers one by one on its
    own SIGHUP)."""
    loop = asyncio.get_running_loop()
    if not hasattr(signal, "SIGHUP") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_hup() -> None:
        loop.run_in_executor(None, reload_now, app)

    loop.add_signal_handler(signal.SIGHUP, on_hup)
    try:
        yield
    finally:
        loop.remove_signal_handler(signal.SIGHUP)


def process_age() -> float | None:
    """Seconds since this process started (Linux's /proc; None elsewhere), for the start-up
    line the image test reads."""
    try:
        with open("/proc/self/stat") as fh:
            start_ticks = int(fh.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as fh:
            uptime = float(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Load the localiser (unless one was given to :func:`create_app`) into the app's
    :class:`ServingMap`; close what the app loaded at the end."""
    state = app.state
    settings: ServerSettings = state.settings
    given: Localizer | None = state.localizer
    observe = state.metrics.batch_size.observe
    loc = given
    if loc is None:
        loc = await run_in_threadpool(load_localizer, settings, observe)
        largest = min(settings.warm_up, settings.batch_max_size)
        await run_in_threadpool(loc.warm_up, largest)

    def swapped(new: Localizer) -> None:
        state.metrics.index_vectors.set(new.info.index.count)

    serving = ServingMap(
        loc,
        settings.index or loc.bundle.path,
        reload_loader(settings, observe),
        drain_s=settings.reload_drain_s,
        on_swap=swapped,
    )
    swapped(loc)
    state.serving = serving
    if settings.foxglove is not None:  # the live view of the answers (docs/TRACKING.md)
        from pnvlad_service.localization.outputs.query_view import open_query_view

        state.query_view = open_query_view(settings.foxglove, settings.index or loc.bundle.path)
    age = process_age()
    prior = loc.prior_config
    log.info(
        "ready: bundle %s (%s, %d vectors), embedding with %s%s; a prior registers to the %d "
        "nearest entries of %s (the map %s)",
        loc.info.index.id,
        loc.info.index.key,
        loc.info.index.count,
        loc.runtime,
        "" if age is None else f" ({age:.2f} s after the process started)",
        prior.max_submaps,
        "one drive" if prior.same_run else "any drive",
        "is aligned" if loc.aligned_map else "is not aligned",
    )
    try:
        with _sighup(app):
            yield
    finally:
        state.serving = None
        if state.query_view is not None:
            state.query_view.close()
            state.query_view = None
        if given is None or serving.current is not given:
            serving.close()  # the caller closes the localiser it gave


def create_app(
    settings: ServerSettings | None = None, localizer: Localizer | None = None
) -> FastAPI:
    """The service app. ``localizer`` (tests) skips loading; else the lifespan loads one."""
    settings = settings or ServerSettings()
    metrics = Metrics()
    # FastAPI's own /docs and /redoc load their assets from a CDN: ours are served locally.
    app = FastAPI(
        title="pnvlad",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    docs.install(app)
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.localizer = localizer  # given (tests), else the lifespan loads one
    app.state.serving = None
    app.state.query_view = None  # pnvlad serve --foxglove: opened by the lifespan
    problems.install(app, on_error=metrics.error)

    # The bearer check is declared (and in the OpenAPI document) only when a key is set.
    protected = [Depends(require_key)] if settings.api_key is not None else []
    app.include_router(localize.router(Contract(settings.limits())), dependencies=protected)
    app.include_router(ops.router(protected))
    app.include_router(admin.router(keyed=(settings.admin_key or settings.api_key) is not None))

    def count(route: str, method: str, status: int) -> None:
        metrics.requests.labels(route, method, str(status)).inc()

    app.add_middleware(
        BodyLimit,
        max_bytes=settings.max_body_bytes,
        on_error=metrics.error,
        on_disconnect=metrics.disconnects.inc,
    )
    app.add_middleware(RequestCounter, count=count)
    return app


def create_app_from_env() -> FastAPI:
    """uvicorn factory (``--factory``): settings from ``PNVLAD_*`` environment variables."""
    return create_app(ServerSettings())
