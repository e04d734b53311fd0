"""Errors as ``application/problem+json`` (RFC 9457).

Every error response has ``type``, ``title``, ``status`` and ``detail``; errors about a field
add ``field`` (e.g. ``points[17]`` or ``top_n``). :class:`Problem` is raised by the HTTP layer
(routes, dependencies, middleware); :func:`install` registers the handlers that turn it,
FastAPI's own errors, the library's :class:`~pnvlad_service.errors.InputError` (422, or 400 for
malformed JSON) and :class:`~pnvlad_service.errors.NotReadyError` (503) and unexpected
exceptions into such responses.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from pnvlad_service.errors import InputError, NotReadyError

log = logging.getLogger(__name__)

PROBLEM_TYPE = "application/problem+json"

#: kind -> (HTTP status, title)
KINDS: dict[str, tuple[int, str]] = {
    "malformed-json": (400, "Malformed JSON"),
    "unauthorized": (401, "Missing or wrong bearer token"),
    "forbidden": (403, "Forbidden"),
    "not-found": (404, "Not found"),
    "method-not-allowed": (405, "Method not allowed"),
    "conflict": (409, "Conflict"),
    "body-too-large": (413, "Request body too large"),
    "unsupported-media-type": (415, "Unsupported content type"),
    "invalid-input": (422, "Invalid input"),
    "not-ready": (503, "Service not ready"),
    "internal": (500, "Internal server error"),
}


class Problem(Exception):
    """An error response of a given ``kind`` (see :data:`KINDS`)."""

    def __init__(
        self,
        kind: str,
        detail: str,
        field: str | None = None,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ) -> None:
        super().__init__(detail)
        self.kind = kind
        self.status, self.title = KINDS[kind]
        self.detail = detail
        self.field = field
        self.headers = headers or {}
        self.extra = extra

    def body(self, instance: str | None = None) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "type": f"urn:pnvlad:problem:{self.kind}",
            "title": self.title,
            "status": self.status,
            "detail": self.detail,
        }
        if instance:
            doc["instance"] = instance
        if self.field:
            doc["field"] = self.field
        doc.update(self.extra)
        return doc

    def encode(self, instance: str | None = None) -> bytes:
        return json.dumps(self.body(instance)).encode()


def from_input_error(exc: InputError) -> Problem:
    """An :class:`InputError` (source = field name) as a 422 problem."""
    field = exc.source
    detail = f"{field}: {exc.detail}" if field else exc.detail
    return Problem("invalid-input", detail, field=field)


PROBLEM_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["type", "title", "status", "detail"],
    "properties": {
        "type": {"type": "string"},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string"},
        "instance": {"type": "string"},
        "field": {"type": "string"},
    },
}


QUERY_REFUSED = (
    "Invalid input: a body or parameter out of its bounds, a combination the fields' "
    "descriptions refuse, a kind of query the map does not hold, verification or a prior asked "
    "of a map without geometry, or a raw scan the filter G cannot use (fewer than 16 points "
    "left after dropping missing returns, cropping and ground removal)"
)


def openapi_responses(
    *statuses: int, described: dict[int, str] | None = None
) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries documenting problem+json bodies for ``statuses``; ``described``:
    a route's own description of some of them (else the problem kind's title)."""
    own = described or {}
    return {
        s: {
            "description": own.get(s) or next(t for st, t in KINDS.values() if st == s),
            "content": {PROBLEM_TYPE: {"schema": PROBLEM_SCHEMA}},
        }
        for s in statuses
    }


def install(app: Any, on_error: Any = None) -> None:
    """Register the exception handlers on a FastAPI ``app``.

    ``on_error(kind)`` is called for every problem response (for metrics).
    """
    from fastapi.exceptions import RequestValidationError
    from starlette.exceptions import HTTPException as StarletteHTTPException
    from starlette.requests import Request
    from starlette.responses import Response

    def respond(request: Request, problem: Problem) -> Response:
        if on_error is not None:
            on_error(problem.kind)
        return Response(
            problem.encode(request.url.path),
            status_code=problem.status,
            media_type=PROBLEM_TYPE,
            headers=problem.headers,
        )

    async def problem_handler(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, Problem)
        return respond(request, exc)

    async def input_handler(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, InputError)
        problem = from_input_error(exc)
        kind = getattr(exc, "problem_kind", None)
        if kind:
            problem.kind = kind
            problem.status, problem.title = KINDS[kind]
        return respond(request, problem)

    async def not_ready_handler(request: Request, exc: Exception) -> Response:
        return respond(request, Problem("not-ready", str(exc)))

    async def validation_handler(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, RequestValidationError)
        errors = exc.errors()
        first = errors[0] if errors else {}
        loc = [str(p) for p in first.get("loc", ()) if p not in ("body", "query", "header")]
        field = ".".join(loc) or None
        msg = first.get("msg", "invalid request")
        detail = f"{field}: {msg}" if field else msg
        return respond(request, Problem("invalid-input", detail, field=field))

    async def http_handler(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, StarletteHTTPException)
        kind = {401: "unauthorized", 404: "not-found", 405: "method-not-allowed"}.get(
            exc.status_code
        )
        if kind is None:
            kind = "invalid-input" if 400 <= exc.status_code < 500 else "internal"
        p = Problem(kind, str(exc.detail), headers=dict(exc.headers or {}))
        p.status = exc.status_code
        return respond(request, p)

    async def unexpected_handler(request: Request, exc: Exception) -> Response:
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return respond(request, Problem("internal", "unexpected server error (see the logs)"))

    app.add_exception_handler(Problem, problem_handler)
    app.add_exception_handler(InputError, input_handler)
    app.add_exception_handler(NotReadyError, not_ready_handler)
    app.add_exception_handler(RequestValidationError, validation_handler)
    app.add_exception_handler(StarletteHTTPException, http_handler)
    app.add_exception_handler(Exception, unexpected_handler)
