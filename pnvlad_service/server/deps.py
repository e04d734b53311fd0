"""The FastAPI dependencies of the routes: the localiser (leased for the whole request), the
serving map, the settings, the metrics and the bearer-token checks. The app keeps them on
``app.state`` (see ``server.app``). They are coroutines so that FastAPI runs them on the event
loop, not in the thread pool."""

from __future__ import annotations

import secrets
from collections.abc import AsyncIterator

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.query.serving import ServingMap
from pnvlad_service.server.metrics import Metrics
from pnvlad_service.server.problems import Problem
from pnvlad_service.server.settings import ServerSettings

bearer = HTTPBearer(auto_error=False, description="The server's PNVLAD_API_KEY.")


async def get_serving(request: Request) -> ServingMap:
    """The app's serving map; 503 ``not-ready`` before the lifespan loaded it or after."""
    serving = request.app.state.serving
    if serving is None:
        raise Problem("not-ready", "model and index are not loaded yet")
    return serving


async def get_localizer(serving: ServingMap = Depends(get_serving)) -> AsyncIterator[Localizer]:
    """The localiser in service, leased for the whole request: a map reload waits for the
    request before it closes the localiser it replaced, and the request's every step (and the
    bundle its answer names) is this one's."""
    with serving.lease() as loc:
        yield loc


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
    _check_bearer(creds, key.get_secret_value(), "the server's API key")


async def require_admin(
    request: Request, creds: HTTPAuthorizationCredentials | None = Depends(bearer)
) -> None:
    """The admin routes' check where a key is configured: ``Authorization: Bearer
    <PNVLAD_ADMIN_KEY>`` (or the API key when no admin key is set), else 401 with
    ``WWW-Authenticate: Bearer``."""
    settings = request.app.state.settings
    key = settings.admin_key or settings.api_key
    assert key is not None
    _check_bearer(creds, key.get_secret_value(), "the server's admin key")


async def admin_off() -> None:
    """The admin routes' answer where neither key is configured: 403 whatever the request
    carries (an open admin route would let anyone point the server at other files). No
    bearer scheme is declared then: no token opens them."""
    raise Problem(
        "forbidden",
        "the admin routes are off: set PNVLAD_ADMIN_KEY (or PNVLAD_API_KEY); SIGHUP reloads "
        "the serving bundle without one",
    )


def _check_bearer(creds: HTTPAuthorizationCredentials | None, key: str, what: str) -> None:
    got = creds.credentials.encode() if creds is not None else b""
    if not secrets.compare_digest(got, key.encode()):
        raise Problem(
            "unauthorized",
            f"send 'Authorization: Bearer <key>' with {what}",
            field="Authorization",
            headers={"WWW-Authenticate": "Bearer"},
        )
