"""Administration: ``POST /admin/reload``, a new map while the server serves.

The bundle named (default: the serving one's path, read again: ``pnvlad index add`` rewrites a
bundle in place) is loaded and checked beside the one in service, then swapped in; queries in
flight finish on the old one, which is then closed
(:class:`~pnvlad_service.localization.query.serving.ServingMap`). A bundle that fails its checks
(missing or corrupt files, a truncated geometry, other weights than the model) is refused with
a 422 naming the file, and the old one keeps serving; a reload while another runs is a 409.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import APIRouter, Depends
from fastapi.concurrency import run_in_threadpool

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.serving import ReloadInProgress, ServingMap
from pnvlad_service.server import problems, schemas
from pnvlad_service.server.deps import admin_off, get_metrics, get_serving, require_admin
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.problems import Problem

log = logging.getLogger(__name__)


async def reload(
    body: schemas.ReloadRequest | None = None,
    serving: ServingMap = Depends(get_serving),
    metrics: Metrics = Depends(get_metrics),
) -> dict[str, Any]:
    """Load a bundle beside the serving one, check it, swap it in, close the old one.

    JSON ``{"index": "/data/index-2", "checkpoint": null}`` (both optional: the serving bundle's
    path read again, the serving model). Answers with the bundle and model before and after. A
    bundle that fails its checks is refused (422 naming the file) and the old one keeps
    serving; 409 while another reload runs."""
    body = body or schemas.ReloadRequest()
    try:
        done = await run_in_threadpool(serving.reload, body.index, body.checkpoint)
    except ReloadInProgress as exc:
        metrics.reloads.labels("busy").inc()
        raise Problem("conflict", str(exc)) from None
    except InputError as exc:
        metrics.reloads.labels("refused").inc()
        log.error("reload refused, still serving %s: %s", serving.current.info.index.id, exc)
        raise
    metrics.reloads.labels("swapped").inc()
    return {**done.to_json(), "runtime": serving.current.runtime}


def router(keyed: bool) -> APIRouter:
    """The admin routes: behind :func:`~pnvlad_service.server.deps.require_admin` (a bearer
    token: 401 without it) when ``keyed`` (an admin or API key is configured), else off
    (:func:`~pnvlad_service.server.deps.admin_off`: 403, no security scheme declared). Both
    answer 400 to a body that is not text and 422 to one that is not a reload request."""
    guard = require_admin if keyed else admin_off
    r = APIRouter(tags=["admin"], dependencies=[Depends(guard)])
    statuses = (400, 401, 403, 409, 422, 503) if keyed else (400, 403, 422)
    r.add_api_route(
        "/admin/reload",
        reload,
        methods=["POST"],
        response_model=schemas.ReloadResponse,
        responses=problems.openapi_responses(*statuses, described=_DESCRIBED),
        summary="Serve another index bundle (or the same path read again) without downtime",
    )
    return r


_DESCRIBED = {
    400: "Bad request: a body that cannot be read as JSON text (not UTF-8)",
    401: "Missing or wrong bearer token (the admin key, else the API key)",
    403: "Forbidden: the admin routes are off (neither PNVLAD_ADMIN_KEY nor PNVLAD_API_KEY set)",
}
