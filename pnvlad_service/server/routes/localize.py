"""Localisation: ``POST /localize`` (one cloud) and ``POST /localize/batch`` (several).

The routes parse, run and write JSON: the body is made the one query type in the thread pool
(:mod:`pnvlad_service.server.bodies`), and the query's path
(:func:`~pnvlad_service.localization.query.run.run`) runs on the event loop with
:data:`THREADS`: the filter G, the parsing and the verification in the thread pool, embedding
and search in the micro-batcher's lanes, awaited.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace
from typing import Any, TypeVar

from fastapi import APIRouter, Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response

from pnvlad_service.localization.query.answers import milliseconds
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.query.run import run, run_many
from pnvlad_service.server import params, problems, schemas
from pnvlad_service.server.bodies import (
    JSON,
    NPY,
    OCTET,
    BinaryParams,
    content_type,
    read_batch,
    read_query,
)
from pnvlad_service.server.contract import Contract
from pnvlad_service.server.deps import get_localizer, get_metrics
from pnvlad_service.server.metrics import Metrics

T = TypeVar("T")
_BINARY_SCHEMA = {"type": "string", "format": "binary"}


class Threads:
    """A query's blocking work in the server's thread pool, the batcher's futures awaited."""

    async def blocking(self, fn: Callable[..., T], *args: Any) -> T:
        return await run_in_threadpool(fn, *args)

    async def wait(self, future: Future[T]) -> T:
        return await asyncio.wrap_future(future)


THREADS = Threads()


def _show(request: Request, answers: list[dict[str, Any]]) -> None:
    """``pnvlad serve --foxglove``: each answer's JSON to the live view."""
    view = request.app.state.query_view
    if view is not None:
        for doc in answers:
            view.answer(doc)


def _post(r: APIRouter, path: str, summary: str, answer: type, content: dict[str, Any]) -> Any:
    """``r.post`` for a localisation route: answered with ``answer`` or one of the problems
    both routes share; its required body is one of ``content``'s media types."""
    return r.post(
        path,
        summary=summary,
        response_model=answer,
        responses=problems.openapi_responses(
            400, 401, 413, 415, 422, 503, described={422: problems.QUERY_REFUSED}
        ),
        openapi_extra={"requestBody": {"required": True, "content": content}},
    )


def router(contract: Contract) -> APIRouter:
    """The two routes, their query parameters and request schemas from ``contract``."""
    r = APIRouter(tags=["localize"])
    binary = {OCTET: {"schema": _BINARY_SCHEMA}, NPY: {"schema": _BINARY_SCHEMA}}

    @_post(
        r,
        "/localize",
        "Localise one point cloud",
        schemas.LocalizeResponse,
        {JSON: {"schema": contract.query_schema()}, **binary},
    )
    async def localize(
        request: Request,
        p: BinaryParams = Depends(params.one_query(contract)),
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
        t0 = time.perf_counter()
        ctype = content_type(request, (JSON, OCTET, NPY))
        body = await request.body()
        p = replace(p, dtype=p.dtype or request.headers.get("x-points-dtype", "float32"))
        parse = functools.partial(read_query, contract, ctype, body, p)
        answer = await run(loc, parse, THREADS, t0=t0)
        metrics.observe(answer.timings.seconds())
        doc = answer.to_json()
        _show(request, [doc])
        return JSONResponse({**doc, **loc.info.to_json()})

    @_post(
        r,
        "/localize/batch",
        "Localise several clouds, embedded as one batch",
        schemas.BatchResponse,
        {JSON: {"schema": contract.batch_schema()}, NPY: binary[NPY]},
    )
    async def localize_batch(
        request: Request,
        p: BinaryParams = Depends(params.batch(contract)),
        loc: Localizer = Depends(get_localizer),
        metrics: Metrics = Depends(get_metrics),
    ) -> Response:
        """Several clouds in one request: JSON ``{"queries": [{"points": ...}, ...],
        "top_n": 5}`` or an ``application/x-npy`` array [B, N, 3] (query parameters
        ``top_n``, ``preprocess``). At most ``max_batch_queries`` clouds."""
        t0 = time.perf_counter()
        ctype = content_type(request, (JSON, NPY))
        body = await request.body()
        queries = await run_in_threadpool(read_batch, contract, ctype, body, p)
        parse_s = time.perf_counter() - t0
        answers = await run_many(loc, queries, THREADS, t0=t0)
        total_s = time.perf_counter() - t0
        for a in answers:
            metrics.observe(a.timings.seconds())
        results = [a.to_json() for a in answers]
        _show(request, results)
        doc: dict[str, Any] = {
            "results": results,
            "timings_ms": {"parse": milliseconds(parse_s), "total": milliseconds(total_s)},
            **loc.info.to_json(),
        }
        return JSONResponse(doc)

    return r
