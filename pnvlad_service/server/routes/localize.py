"""Localisation: ``POST /localize`` (one cloud) and ``POST /localize/batch`` (several).

The routes only parse, call and serialise: the body is read into validated clouds in the
thread pool (:mod:`pnvlad_service.server.bodies`), the filter G runs in the thread pool
(``Localizer.prepare``), embedding and search in the micro-batcher's lanes
(``Localizer.submit``, awaited), verification of the top candidates in the thread pool
(``Localizer.verify``), and the typed answers are written as JSON.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any, NamedTuple

from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.answers import milliseconds
from pnvlad_service.localization.query.limits import MAX_RUN_CHARS
from pnvlad_service.localization.query.localizer import Localizer, PreparedCloud
from pnvlad_service.server import problems, schemas
from pnvlad_service.server.bodies import JSON, NPY, OCTET, read_batch, read_query
from pnvlad_service.server.contract import Contract
from pnvlad_service.server.contract import Query as Cloud
from pnvlad_service.server.deps import get_localizer, get_metrics
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.problems import Problem

_BINARY_SCHEMA = {"type": "string", "format": "binary"}


def _content_type(request: Request, allowed: tuple[str, ...]) -> str:
    """The request's media type, one of ``allowed``; 415 else."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in allowed:
        *first, last = allowed
        send = f"{', '.join(first)} or {last}" if first else last
        raise Problem(
            "unsupported-media-type",
            f"content type {ctype or '(none)'!r} is not supported; send {send}",
            field="Content-Type",
        )
    return ctype


async def _prepare(loc: Localizer, cloud: Cloud, field: str) -> PreparedCloud:
    """The encoder's input of one cloud; a raw scan goes through the filter G in the thread
    pool, and its refusal names ``field``."""
    if not cloud.preprocess:
        return loc.prepare(cloud.points, False, cloud.scale)
    try:
        return await run_in_threadpool(loc.prepare, cloud.points, True)
    except InputError as exc:
        raise InputError(f"filter G: {exc.detail}", field) from None


async def _verified(loc: Localizer, prepared: PreparedCloud, result: Any, verify: bool) -> Any:
    """The verification of one query (in the thread pool), or ``None`` when not asked."""
    if not verify:
        return None
    return await run_in_threadpool(loc.verify, prepared, result)


async def localize_one(
    request: Request,
    contract: Contract,
    loc: Localizer,
    metrics: Metrics,
    params: tuple[Any, ...],
) -> Response:
    """``POST /localize``; ``params``: the query's ``top_n``, ``preprocess``, ``dtype``,
    ``verify``, ``scale``, ``kind`` and ``prior`` (a dict of the prior's query parameters)."""
    t0 = time.perf_counter()
    ctype = _content_type(request, (JSON, OCTET, NPY))
    body = await request.body()
    top_n, preprocess, dtype, verify, scale, kind, prior = params
    dtype = dtype or request.headers.get("x-points-dtype", "float32")
    with loc.announce():
        cloud = await run_in_threadpool(
            read_query, contract, ctype, body, top_n, preprocess, dtype, verify, scale, kind, prior
        )
        loc.check_kind(cloud.kind)
        if cloud.prior is None:
            parse_s = time.perf_counter() - t0
            wants = loc.wants_verify(cloud.verify)
            t1 = time.perf_counter()
            prepared = await _prepare(loc, cloud, "points")
            preprocess_s = time.perf_counter() - t1
            future = loc.submit(prepared, loc.search_k(cloud.top_n, wants))
    if cloud.prior is not None:
        return await localize_near(loc, metrics, cloud, t0)
    result = await asyncio.wrap_future(future)
    verification = await _verified(loc, prepared, result, wants)
    answer = loc.answer(
        result,
        parse_s=parse_s,
        preprocess_s=preprocess_s,
        total_s=time.perf_counter() - t0,
        top_n=cloud.top_n,
        verification=verification,
        query_kind=cloud.kind,
    )
    metrics.observe(answer.timings.seconds())
    return JSONResponse({**answer.to_json(), **loc.info.to_json()})


async def localize_near(loc: Localizer, metrics: Metrics, cloud: Cloud, t0: float) -> Response:
    """``POST /localize`` with a prior pose: G, then the registration to the map near the
    prior (in the thread pool; in the verification process when the server has one)."""
    loc.check_prior(cloud.kind, cloud.verify)
    parse_s = time.perf_counter() - t0
    prepared = await _prepare(loc, cloud, "points")
    preprocess_s = time.perf_counter() - t0 - parse_s
    fit = await run_in_threadpool(loc.register_near, prepared, cloud.prior)
    answer = loc.answer_near(
        fit,
        parse_s=parse_s,
        preprocess_s=preprocess_s,
        total_s=time.perf_counter() - t0,
        top_n=cloud.top_n,
        query_kind=cloud.kind,
    )
    metrics.observe(answer.timings.seconds())
    return JSONResponse({**answer.to_json(), **loc.info.to_json()})


async def localize_many(
    request: Request,
    contract: Contract,
    loc: Localizer,
    metrics: Metrics,
    params: tuple[int | None, bool | None, bool | None],
) -> Response:
    """``POST /localize/batch``; ``params``: the query's ``top_n``, ``preprocess`` and
    ``verify``."""
    t0 = time.perf_counter()
    ctype = _content_type(request, (JSON, NPY))
    body = await request.body()
    batch = await run_in_threadpool(read_batch, contract, ctype, body, *params)
    for i, q in enumerate(batch.queries):
        loc.check_kind(q.kind, f"queries[{i}].kind")
    parse_s = time.perf_counter() - t0
    wants = loc.wants_verify(batch.verify)
    t1 = time.perf_counter()
    prepared = [await _prepare(loc, q, f"queries[{i}].points") for i, q in enumerate(batch.queries)]
    preprocess_s = (time.perf_counter() - t1) / len(prepared)
    futures = [loc.submit(c, loc.search_k(batch.top_n, wants)) for c in prepared]
    results = await asyncio.gather(*(asyncio.wrap_future(f) for f in futures))
    checks = [await _verified(loc, p, r, wants) for p, r in zip(prepared, results, strict=True)]
    total_s = time.perf_counter() - t0
    answers = [
        loc.answer(
            r,
            parse_s=parse_s,
            preprocess_s=preprocess_s,
            total_s=total_s,
            top_n=batch.top_n,
            verification=v,
            query_kind=q.kind,
        )
        for r, v, q in zip(results, checks, batch.queries, strict=True)
    ]
    for a in answers:
        metrics.observe(a.timings.seconds())
    doc: dict[str, Any] = {
        "results": [a.to_json() for a in answers],
        "timings_ms": {"parse": milliseconds(parse_s), "total": milliseconds(total_s)},
        **loc.info.to_json(),
    }
    return JSONResponse(doc)


def _post(r: APIRouter, path: str, summary: str, answer: type, content: dict[str, Any]) -> Any:
    """``r.post`` for a localisation route: answered with ``answer`` or one of the problems
    both routes share; its required body is one of ``content``'s media types."""
    return r.post(
        path,
        summary=summary,
        response_model=answer,
        responses=problems.openapi_responses(400, 401, 413, 415, 422, 503),
        openapi_extra={"requestBody": {"required": True, "content": content}},
    )


def _prior_params(contract: Contract) -> dict[str, Any]:
    """The ``prior_*`` query parameters of binary bodies, by the field they fill."""
    radius = contract.limits.max_prior_radius_m
    coord = contract.limits.max_prior_coord
    return {
        "northing": Query(
            None,
            ge=-coord,
            le=coord,
            description="Prior pose of the sensor (binary bodies), UTM metres: with "
            "prior_easting and prior_yaw_deg the scan is registered to the map entries near it, "
            "no retrieval (mode 'prior'; raw scans only).",
        ),
        "easting": Query(None, ge=-coord, le=coord, description="Prior pose: UTM metres."),
        "yaw_deg": Query(
            None,
            ge=-360.0,
            le=360.0,
            description="Prior pose: heading of the sensor's x axis, degrees from east.",
        ),
        "height": Query(
            None,
            ge=-contract.limits.max_raw_coord,
            le=contract.limits.max_raw_coord,
            description="Prior pose: metres (default: the map's).",
        ),
        "radius_m": Query(
            None,
            gt=0.0,
            le=radius,
            description=f"Prior pose: map entries within this many metres are registered to "
            f"(at most {radius:g}; default {contract.limits.default_prior_radius_m:g}).",
        ),
        "run": Query(
            None,
            min_length=1,
            max_length=MAX_RUN_CHARS,
            description="Prior pose: the map's drive (dataset/run) to register to when it has "
            "entries within the radius (the last answer's).",
        ),
    }


class _Params(NamedTuple):
    """The query parameters of binary bodies, as FastAPI declares them (their descriptions are
    the OpenAPI document's)."""

    top_n: Any
    preprocess: Any
    verify: Any
    scale: Any
    kind: Any
    dtype: Any
    prior: dict[str, Any]


def _params(contract: Contract) -> _Params:
    """The routes' query parameters, bounded by ``contract``'s limits."""
    return _Params(
        top_n=Query(
            None,
            ge=1,
            le=contract.limits.max_top_n,
            description="Matches to return (binary bodies).",
        ),
        preprocess=Query(None, description="Raw scan: run the filter G first (binary bodies)."),
        verify=Query(
            None,
            description="Register the top candidates and re-rank them (binary bodies; default: "
            "when the index carries geometry).",
        ),
        scale=Query(
            None,
            gt=0,
            le=contract.limits.max_scale,
            description="Metres per unit of a preprocessed cloud, for a metric pose (binary "
            "bodies).",
        ),
        kind=Query(
            None,
            pattern="^(submap|scan|window)$",
            description="What the cloud is (binary bodies): 'submap' (4096 preprocessed points), "
            "'scan' (one raw scan, sensor frame, metres) or 'window' (raw scans accumulated over "
            "the last stretch of a drive, in the newest scan's frame); scan and window are raw "
            "(the filter G runs first). Default: 'scan' with preprocess=true, else 'submap'. A "
            "map of keyframes refuses windows (422).",
        ),
        dtype=Query(
            None,
            pattern="^(float32|float64)$",
            description="Element type of an application/octet-stream body (default float32; "
            "or the header X-Points-Dtype).",
        ),
        prior=_prior_params(contract),
    )


def router(contract: Contract) -> APIRouter:
    """The two routes, their query parameters and request schemas from ``contract``."""
    r = APIRouter(tags=["localize"])
    q = _params(contract)

    @_post(
        r,
        "/localize",
        "Localise one point cloud",
        schemas.LocalizeResponse,
        {
            JSON: {"schema": contract.query_schema()},
            OCTET: {"schema": _BINARY_SCHEMA},
            NPY: {"schema": _BINARY_SCHEMA},
        },
    )
    async def localize(
        request: Request,
        top_n: int | None = q.top_n,
        preprocess: bool | None = q.preprocess,
        dtype: str | None = q.dtype,
        verify: bool | None = q.verify,
        scale: float | None = q.scale,
        kind: str | None = q.kind,
        prior_northing: float | None = q.prior["northing"],
        prior_easting: float | None = q.prior["easting"],
        prior_yaw_deg: float | None = q.prior["yaw_deg"],
        prior_height: float | None = q.prior["height"],
        prior_radius_m: float | None = q.prior["radius_m"],
        prior_run: str | None = q.prior["run"],
        loc: Localizer = Depends(get_localizer),
        metrics: Metrics = Depends(get_metrics),
    ) -> Response:
        """Find the map places nearest to one cloud.

        JSON ``{"points": [[x, y, z], ...], "top_n": 5, "preprocess": false}`` with exactly
        4096 preprocessed points, or a raw scan with ``preprocess: true``. When the index
        carries geometry the top candidates are registered to the query and re-ranked; the
        answer says whether the best is ``verified`` and gives the query's ``pose`` (``verify:
        false`` skips it; ``scale``: metres per unit of a preprocessed cloud). Binary bodies:
        ``application/octet-stream`` (little-endian xyz, float32 unless ``dtype=float64``) or
        ``application/x-npy`` ([N, 3]); then ``top_n`` and ``preprocess`` are query parameters.

        With a prior pose (``"prior": {"northing", "easting", "yaw_deg", "height",
        "radius_m"}``, or the ``prior_*`` query parameters) a raw scan is not searched for:
        it is registered to the map entries within the radius of the prior, and the answer
        (``mode: "prior"``) gives its pose with a covariance when it fits
        (docs/TRACKING.md).
        """
        prior = {
            "northing": prior_northing,
            "easting": prior_easting,
            "yaw_deg": prior_yaw_deg,
            "height": prior_height,
            "radius_m": prior_radius_m,
            "run": prior_run,
        }
        params = (top_n, preprocess, dtype, verify, scale, kind, prior)
        return await localize_one(request, contract, loc, metrics, params)

    @_post(
        r,
        "/localize/batch",
        "Localise several clouds, embedded as one batch",
        schemas.BatchResponse,
        {JSON: {"schema": contract.batch_schema()}, NPY: {"schema": _BINARY_SCHEMA}},
    )
    async def localize_batch(
        request: Request,
        top_n: int | None = q.top_n,
        preprocess: bool | None = q.preprocess,
        verify: bool | None = q.verify,
        loc: Localizer = Depends(get_localizer),
        metrics: Metrics = Depends(get_metrics),
    ) -> Response:
        """Several clouds in one request: JSON ``{"queries": [{"points": ...}, ...],
        "top_n": 5}`` or an ``application/x-npy`` array [B, N, 3] (query parameters
        ``top_n``, ``preprocess``). At most ``max_batch_queries`` clouds."""
        return await localize_many(request, contract, loc, metrics, (top_n, preprocess, verify))

    return r
