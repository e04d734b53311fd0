"""Operations: ``GET /healthz``, ``/readyz``, ``/info`` and ``/metrics``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends
from fastapi.params import Depends as DependsParam
from fastapi.responses import Response

from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.server import problems, schemas
from pnvlad_service.server.deps import get_localizer, get_metrics, get_settings
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.settings import ServerSettings


def healthz() -> dict[str, str]:
    """Liveness: the process answers."""
    return {"status": "ok"}


def readyz(loc: Localizer = Depends(get_localizer)) -> dict[str, Any]:
    """Readiness: model and index are loaded. Says what embeds (ONNX Runtime or torch, its
    version and threads) and which bundle serves."""
    return {"status": "ready", "runtime": loc.runtime, "index": loc.info.to_json()["index"]}


def info(
    loc: Localizer = Depends(get_localizer), settings: ServerSettings = Depends(get_settings)
) -> dict[str, Any]:
    """The bundle's manifest, the UTM zone of its map, the model, the runtime, the request
    limits and how a prior pose is registered."""
    prior = loc.prior_config
    return {
        "manifest": loc.manifest_json(),
        "utm_zone": loc.utm_zone,
        "model": loc.identity.to_json(),
        "runtime": loc.runtime,
        "limits": {"max_body_bytes": settings.max_body_bytes, **settings.limits().to_json()},
        "prior": {
            "aligned_map": loc.aligned_map,
            "same_run": prior.same_run,
            "max_submaps": prior.max_submaps,
            "retry_submaps": prior.retry_submaps,
            "min_fitness": prior.min_fitness,
            "max_sigma_m": prior.max_sigma_m,
        },
    }


def prometheus(metrics: Metrics = Depends(get_metrics)) -> Response:
    """Prometheus metrics: requests, latency by stage, errors by kind, batch sizes."""
    data, ctype = metrics.render()
    return Response(data, media_type=ctype)


def router(protected: list[DependsParam]) -> APIRouter:
    """The routes; ``protected`` (the bearer check, when a key is set) guards ``/info``."""
    r = APIRouter(tags=["ops"])
    r.add_api_route("/healthz", healthz, methods=["GET"], response_model=schemas.Health)
    r.add_api_route(
        "/readyz",
        readyz,
        methods=["GET"],
        response_model=schemas.Ready,
        responses=problems.openapi_responses(503),
    )
    r.add_api_route(
        "/info",
        info,
        methods=["GET"],
        response_model=schemas.Info,
        responses=problems.openapi_responses(401, 503),
        dependencies=protected,
    )
    r.add_api_route(
        "/metrics",
        prometheus,
        methods=["GET"],
        response_class=Response,
        responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}},
    )
    return r
