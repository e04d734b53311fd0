"""The FastAPI app: ``create_app(settings)``; ``create_app_from_env()`` for uvicorn's factory.

Routes: ``POST /localize`` (JSON, raw float32/float64 xyz, or ``.npy``), ``POST /localize/batch``,
``GET /healthz``, ``GET /readyz``, ``GET /info``, ``GET /metrics`` and the OpenAPI docs at
``/docs``. Errors are ``application/problem+json``. Bodies are bounded while read
(:class:`~pnvlad_service.server.middleware.BodyLimit`); parsing and the filter G run in the
thread pool and embedding plus search in the micro-batcher's thread, off the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import AsyncIterator
from typing import Any

from fastapi import Depends, FastAPI, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from pnvlad_service import __version__
from pnvlad_service.errors import InputError
from pnvlad_service.server import problems, schemas
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.middleware import BodyLimit, RequestCounter
from pnvlad_service.server.problems import Problem
from pnvlad_service.server.service import (
    Localizer,
    check_points,
    parse_binary_points,
    parse_json_batch,
    parse_json_query,
    parse_npy,
)
from pnvlad_service.server.settings import ServerSettings

log = logging.getLogger(__name__)

JSON = "application/json"
OCTET = "application/octet-stream"
NPY = "application/x-npy"

_BINARY_SCHEMA = {"type": "string", "format": "binary"}


def _ms(timings: dict[str, float]) -> dict[str, float]:
    return {k: round(v * 1000.0, 3) for k, v in timings.items()}


def _content_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def create_app(
    settings: ServerSettings | None = None, localizer: Localizer | None = None
) -> FastAPI:
    """The service app. ``localizer`` (tests) skips loading; else the lifespan loads one."""
    settings = settings or ServerSettings()
    metrics = Metrics()
    state: dict[str, Any] = {"localizer": localizer}

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owned = state["localizer"] is None
        if owned:
            state["localizer"] = await run_in_threadpool(
                Localizer.load, settings, metrics.batch_size.observe
            )
        loc: Localizer = state["localizer"]
        metrics.index_vectors.set(loc.bundle.count)
        app.state.localizer = loc
        try:
            yield
        finally:
            if owned:
                loc.close()
                state["localizer"] = None

    app = FastAPI(
        title="pnvlad",
        version=__version__,
        description=(
            "LiDAR place recognition: send a point cloud, get the nearest places of the map "
            "(UTM northing/easting) with their descriptor distances."
        ),
        lifespan=lifespan,
    )
    problems.install(app, on_error=metrics.error)

    bearer = HTTPBearer(auto_error=False, description="The server's PNVLAD_API_KEY.")

    def check_key(
        creds: HTTPAuthorizationCredentials | None = Depends(bearer),
    ) -> None:
        assert settings.api_key is not None
        want = settings.api_key.get_secret_value().encode()
        got = creds.credentials.encode() if creds is not None else b""
        if not secrets.compare_digest(got, want):
            raise Problem(
                "unauthorized",
                "send 'Authorization: Bearer <key>' with the server's API key",
                field="Authorization",
                headers={"WWW-Authenticate": "Bearer"},
            )

    # Declared (and in the OpenAPI document) only when a key is configured.
    protected = [Depends(check_key)] if settings.api_key is not None else []

    def get_localizer() -> Localizer:
        loc = state["localizer"]
        if loc is None:
            raise Problem("not-ready", "model and index are not loaded yet")
        return loc

    async def submit(
        loc: Localizer,
        clouds: list[tuple[Any, bool]],
        top_n: int,
        timings: dict[str, float],
        batch: bool = False,
    ) -> list[Any]:
        """Preprocess raw scans (thread pool) and queue every cloud; returns the futures."""
        t0 = time.perf_counter()
        prepared = []
        for i, (pts, pre) in enumerate(clouds):
            if not pre:
                prepared.append(pts)
                continue
            try:
                prepared.append(await run_in_threadpool(loc.preprocess, pts))
            except InputError as exc:  # name the cloud the filter G refused
                field = f"queries[{i}].points" if batch else "points"
                raise InputError(f"filter G: {exc.detail}", field) from None
        timings["preprocess"] = time.perf_counter() - t0
        return [loc.batcher.submit(c, top_n) for c in prepared]

    async def collect(
        loc: Localizer, futures: list[Any], timings: dict[str, float]
    ) -> list[dict[str, Any]]:
        """Wait for the batcher's answers; each gets its own copy of the stage timings."""
        results = await asyncio.gather(*(asyncio.wrap_future(f) for f in futures))
        out = []
        for r in results:
            t = {"parse": timings["parse"], "preprocess": timings["preprocess"] / len(results)}
            answer = loc.answer(r, t)
            answer["timings"] = t
            out.append(answer)
        return out

    query_top_n = Query(
        None, ge=1, le=settings.max_top_n, description="Matches to return (binary bodies)."
    )
    query_pre = Query(None, description="Raw scan: run the filter G first (binary bodies).")
    query_dtype = Query(
        None,
        pattern="^(float32|float64)$",
        description="Element type of an application/octet-stream body (default float32; "
        "or the header X-Points-Dtype).",
    )

    @app.post(
        "/localize",
        tags=["localize"],
        summary="Localise one point cloud",
        response_model=schemas.LocalizeResponse,
        responses=problems.openapi_responses(400, 401, 413, 415, 422, 503),
        dependencies=protected,
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {
                    JSON: {
                        "schema": schemas.localize_request_schema(
                            settings.max_top_n, settings.max_raw_points
                        )
                    },
                    OCTET: {"schema": _BINARY_SCHEMA},
                    NPY: {"schema": _BINARY_SCHEMA},
                },
            }
        },
    )
    async def localize(
        request: Request,
        top_n: int | None = query_top_n,
        preprocess: bool | None = query_pre,
        dtype: str | None = query_dtype,
    ) -> Response:
        """Find the map places nearest to one cloud.

        JSON ``{"points": [[x, y, z], ...], "top_n": 5, "preprocess": false}`` with exactly
        4096 preprocessed points, or a raw scan with ``preprocess: true``. Binary bodies:
        ``application/octet-stream`` (little-endian xyz, float32 unless ``dtype=float64``) or
        ``application/x-npy`` ([N, 3]); then ``top_n`` and ``preprocess`` are query parameters.
        """
        loc = get_localizer()
        t0 = time.perf_counter()
        ctype = _content_type(request)
        if ctype not in (JSON, OCTET, NPY):
            raise Problem(
                "unsupported-media-type",
                f"content type {ctype or '(none)'!r} is not supported; send {JSON}, "
                f"{OCTET} or {NPY}",
                field="Content-Type",
            )
        body = await request.body()
        s = settings
        with loc.batcher.announce():
            if ctype == JSON:
                pts, n, pre = await run_in_threadpool(
                    parse_json_query, body, s.max_top_n, s.max_raw_points
                )
            else:
                pre = bool(preprocess)
                n = top_n if top_n is not None else 5
                dt = dtype or request.headers.get("x-points-dtype", "float32")

                def parse() -> Any:
                    raw = parse_npy(body, 2) if ctype == NPY else parse_binary_points(body, dt)
                    return check_points(raw, pre, "body", s.max_raw_points)

                pts = await run_in_threadpool(parse)
            timings = {"parse": time.perf_counter() - t0}
            futures = await submit(loc, [(pts, pre)], n, timings)
        (answer,) = await collect(loc, futures, timings)
        t = answer.pop("timings")
        t["total"] = time.perf_counter() - t0
        metrics.observe(t)
        answer["timings_ms"] = _ms(t)
        answer["model"] = loc.model_info()
        answer["index"] = loc.index_info()
        return JSONResponse(answer)

    @app.post(
        "/localize/batch",
        tags=["localize"],
        summary="Localise several clouds, embedded as one batch",
        response_model=schemas.BatchResponse,
        responses=problems.openapi_responses(400, 401, 413, 415, 422, 503),
        dependencies=protected,
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {
                    JSON: {
                        "schema": schemas.batch_request_schema(
                            settings.max_top_n, settings.max_raw_points, settings.max_batch_queries
                        )
                    },
                    NPY: {"schema": _BINARY_SCHEMA},
                },
            }
        },
    )
    async def localize_batch(
        request: Request,
        top_n: int | None = query_top_n,
        preprocess: bool | None = query_pre,
    ) -> Response:
        """Several clouds in one request: JSON ``{"queries": [{"points": ...}, ...],
        "top_n": 5}`` or an ``application/x-npy`` array [B, N, 3] (query parameters
        ``top_n``, ``preprocess``). At most ``max_batch_queries`` clouds."""
        loc = get_localizer()
        t0 = time.perf_counter()
        ctype = _content_type(request)
        if ctype not in (JSON, NPY):
            raise Problem(
                "unsupported-media-type",
                f"content type {ctype or '(none)'!r} is not supported; send {JSON} or {NPY}",
                field="Content-Type",
            )
        body = await request.body()
        s = settings
        if ctype == JSON:
            clouds, n = await run_in_threadpool(
                parse_json_batch, body, s.max_top_n, s.max_raw_points, s.max_batch_queries
            )
        else:
            pre = bool(preprocess)
            n = top_n if top_n is not None else 5

            def parse() -> list[tuple[Any, bool]]:
                arr = parse_npy(body, 3)
                if not 1 <= len(arr) <= s.max_batch_queries:
                    raise InputError(
                        f"expected 1 to {s.max_batch_queries} clouds, got {len(arr)}", "body"
                    )
                return [
                    (check_points(a, pre, f"body[{i}]", s.max_raw_points), pre)
                    for i, a in enumerate(arr)
                ]

            clouds = await run_in_threadpool(parse)
        timings = {"parse": time.perf_counter() - t0}
        answers = await collect(loc, await submit(loc, clouds, n, timings, batch=True), timings)
        total = time.perf_counter() - t0
        for a in answers:
            t = a.pop("timings")
            t["total"] = total
            metrics.observe(t)
            a["timings_ms"] = _ms(t)
        return JSONResponse(
            {
                "results": answers,
                "timings_ms": _ms({"parse": timings["parse"], "total": total}),
                "model": loc.model_info(),
                "index": loc.index_info(),
            }
        )

    @app.get("/healthz", tags=["ops"], response_model=schemas.Health)
    def healthz() -> dict[str, str]:
        """Liveness: the process answers."""
        return {"status": "ok"}

    @app.get(
        "/readyz",
        tags=["ops"],
        response_model=schemas.Health,
        responses=problems.openapi_responses(503),
    )
    def readyz() -> dict[str, str]:
        """Readiness: model and index are loaded."""
        get_localizer()
        return {"status": "ready"}

    @app.get(
        "/info",
        tags=["ops"],
        response_model=schemas.Info,
        responses=problems.openapi_responses(401, 503),
        dependencies=protected,
    )
    def info() -> dict[str, Any]:
        """The bundle's manifest, the model and the request limits."""
        loc = get_localizer()
        return {
            "manifest": loc.bundle.manifest.to_json(),
            "model": loc.model,
            "limits": {
                "max_body_bytes": settings.max_body_bytes,
                "max_raw_points": settings.max_raw_points,
                "max_top_n": settings.max_top_n,
                "max_batch_queries": settings.max_batch_queries,
                "points_per_cloud": 4096,
            },
        }

    @app.get(
        "/metrics",
        tags=["ops"],
        response_class=Response,
        responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}},
    )
    def prometheus() -> Response:
        """Prometheus metrics: requests, latency by stage, errors by kind, batch sizes."""
        data, ctype = metrics.render()
        return Response(data, media_type=ctype)

    def count(route: str, method: str, status: int) -> None:
        metrics.requests.labels(route, method, str(status)).inc()

    app.add_middleware(
        BodyLimit,
        max_bytes=settings.max_body_bytes,
        on_error=metrics.error,
        on_disconnect=metrics.disconnects.inc,
    )
    app.add_middleware(RequestCounter, count=count)
    app.state.metrics = metrics
    app.state.settings = settings
    return app


def create_app_from_env() -> FastAPI:
    """uvicorn factory (``--factory``): settings from ``PNVLAD_*`` environment variables."""
    return create_app(ServerSettings())
