"""The FastAPI dependencies of the routes: the localiser, the settings, the metrics and the
bearer-token check. The app keeps the three objects on ``app.state`` (see ``server.app``).
They are coroutines so that FastAPI runs them on the event loop, not in the thread pool."""

from __future__ import annotations

import secrets

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from pnvlad_service.localization.localizer import Localizer
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.problems import Problem
from pnvlad_service.server.settings import ServerSettings

bearer = HTTPBearer(auto_error=False, description="The server's PNVLAD_API_KEY.")


async def get_localizer(request: Request) -> Localizer:
    """The loaded localiser; 503 ``not-ready`` before the lifespan loaded it or after close."""
    loc = request.app.state.localizer
    if loc is None:
        raise Problem("not-ready", "model and index are not loaded yet")
    return loc


async def get_settings(request: Request) -> ServerSettings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def require_key(
    request: Request, creds: HTTPAuthorizationCredentials | None = Depends(bearer)
) -> None:
    """401 unless the request carries ``Authorization: Bearer <the server's API key>``.
    Declared (and so in the OpenAPI document) only where a key is configured."""
    key = request.app.state.settings.api_key
    assert key is not None
    got = creds.credentials.encode() if creds is not None else b""
    if not secrets.compare_digest(got, key.get_secret_value().encode()):
        raise Problem(
            "unauthorized",
            "send 'Authorization: Bearer <key>' with the server's API key",
            field="Authorization",
            headers={"WWW-Authenticate": "Bearer"},
        )
