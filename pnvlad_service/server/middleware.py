"""Small pure-ASGI middlewares: a bounded request body and per-route request counts.

FastAPI has no body-size limit. :class:`BodyLimit` reads the body itself, counting the bytes of
``http.request`` messages (never trusting ``Content-Length``, though a declared length over the
limit is refused at once), answers 413 as soon as the limit is passed, and hands the app a
replay of the buffered body. A client that disconnects mid-body gets no response and the app is
never called.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from pnvlad_service.server.problems import PROBLEM_TYPE, Problem

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


async def _send_problem(send: Send, problem: Problem, path: str) -> None:
    body = problem.encode(path)
    await send(
        {
            "type": "http.response.start",
            "status": problem.status,
            "headers": [
                (b"content-type", PROBLEM_TYPE.encode()),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """Buffer request bodies up to ``max_bytes``; 413 beyond it."""

    def __init__(
        self,
        app: ASGIApp,
        max_bytes: int,
        on_error: Callable[[str], None] | None = None,
        on_disconnect: Callable[[], None] | None = None,
    ) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.on_error = on_error
        self.on_disconnect = on_disconnect

    def _too_large(self, size: str) -> Problem:
        if self.on_error:
            self.on_error("body-too-large")
        return Problem(
            "body-too-large",
            f"body: {size} bytes is over the limit of {self.max_bytes} bytes",
            field="body",
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope.get("path", "")
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    declared = -1
                if declared > self.max_bytes:
                    await _send_problem(send, self._too_large(str(declared)), path)
                    return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                if self.on_disconnect:
                    self.on_disconnect()
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                await _send_problem(send, self._too_large(f"more than {self.max_bytes}"), path)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class RequestCounter:
    """Count responses by route template (not raw path: bounded label values) and status."""

    def __init__(self, app: ASGIApp, count: Callable[[str, str, int], None]) -> None:
        self.app = app
        self.count = count

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 0

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            if status:
                route = scope.get("route")
                template = getattr(route, "path", None) or "other"
                method = scope.get("method", "")
                if method not in {"GET", "POST", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH"}:
                    method = "other"
                self.count(template, method, status)
