"""The FastAPI app: ``create_app(settings)``; ``create_app_from_env()`` for uvicorn's factory.

Routes (one router per resource, :mod:`pnvlad_service.server.routes`): ``POST /localize``
(JSON, raw float32/float64 xyz, or ``.npy``), ``POST /localize/batch``, ``GET /healthz``,
``GET /readyz``, ``GET /info``, ``GET /metrics`` and the API docs at ``/docs`` and ``/redoc``
(served from installed assets, :mod:`pnvlad_service.server.docs`). Errors are
``application/problem+json``. Bodies are bounded while read
(:class:`~pnvlad_service.server.middleware.BodyLimit`). The lifespan loads the
:class:`~pnvlad_service.localization.localizer.Localizer` once, in the thread pool; the routes
get it, the settings and the metrics through :mod:`pnvlad_service.server.deps`.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator, Callable

from fastapi import Depends, FastAPI
from fastapi.concurrency import run_in_threadpool

from pnvlad_service import __version__
from pnvlad_service.errors import InputError
from pnvlad_service.localization.localizer import Localizer, set_threads
from pnvlad_service.server import docs, problems
from pnvlad_service.server.contract import Contract
from pnvlad_service.server.deps import require_key
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.middleware import BodyLimit, RequestCounter
from pnvlad_service.server.routes import localize, ops
from pnvlad_service.server.settings import ServerSettings

log = logging.getLogger(__name__)

DESCRIPTION = (
    "LiDAR place recognition: send a point cloud, get the nearest places of the map "
    "(UTM northing/easting) with their descriptor distances."
)


def load_localizer(
    settings: ServerSettings, on_batch: Callable[[int], None] | None = None
) -> Localizer:
    """The localiser that ``settings`` name (bundle, model, device, threads, batching)."""
    set_threads(settings.torch_threads, settings.faiss_threads)
    if settings.index is None:
        raise InputError("no index bundle given (--index or PNVLAD_INDEX)", "index")
    return Localizer.load(
        settings.index,
        settings.checkpoint,
        device=settings.device,
        verify=settings.verify_bundle,
        batching=settings.batching(),
        on_batch=on_batch,
        verify_config=settings.verify_config(),
        verify_process=settings.verify_process,
        threshold=settings.verify_threshold,
        prior_config=settings.prior_config(),
    )


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Load the localiser (unless one was given to :func:`create_app`), close it at the end."""
    state = app.state
    owned = state.localizer is None
    if owned:
        state.localizer = await run_in_threadpool(
            load_localizer, state.settings, state.metrics.batch_size.observe
        )
    loc: Localizer = state.localizer
    if owned:
        largest = min(state.settings.warm_up, state.settings.batch_max_size)
        await run_in_threadpool(loc.warm_up, largest)
    state.metrics.index_vectors.set(loc.info.index.count)
    try:
        yield
    finally:
        if owned:
            state.localizer = None
            loc.close()


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
    app.state.localizer = localizer
    problems.install(app, on_error=metrics.error)

    # The bearer check is declared (and in the OpenAPI document) only when a key is set.
    protected = [Depends(require_key)] if settings.api_key is not None else []
    app.include_router(localize.router(Contract(settings.limits())), dependencies=protected)
    app.include_router(ops.router(protected))

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
