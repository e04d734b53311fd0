"""The HTTP client of ``pnvlad serve`` (standard library and numpy only): one keep-alive
connection. ``from pnvlad_service.client import LocalizeClient``.

:class:`LocalizeClient` sends a cloud as a binary body (little-endian xyz, float64 when the
array is float64, else float32) and returns the server's JSON answer; ``ready()`` and
``info()`` ask the operations routes. A refused request (4xx) raises
:class:`ServerRefused` (an ``InputError``), any other failure :class:`ServerError`, both with
the problem's ``detail`` and the status. One client is not thread-safe: one per thread.
"""

from __future__ import annotations

import http.client
import json
import urllib.parse
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError, PnvladError

_RETRY = (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError)


class ServerError(PnvladError):
    """The server answered an error (``status``, its problem document) or could not be
    reached (``status`` None)."""

    def __init__(
        self, url: str, message: str, status: int | None = None, problem: Any = None
    ) -> None:
        super().__init__(f"{url}: {message}")
        self.url, self.status, self.problem = url, status, problem


class ServerRefused(InputError):
    """The server refused the request (4xx): the input was wrong (the detail says what)."""

    def __init__(self, url: str, message: str, status: int, problem: Any = None) -> None:
        super().__init__(message, source=url)
        self.url, self.status, self.problem = url, status, problem


class LocalizeClient:
    """A client of the server at ``url`` (``http://host:port`` with an optional path prefix);
    ``api_key``: the bearer token; ``timeout``: seconds per request."""

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 120.0) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise InputError("expected an http:// or https:// URL", source=url)
        self.url = url
        self.timeout = timeout
        self._parts = parts
        self._prefix = parts.path.rstrip("/")
        self._headers = {"Accept": "application/json"}
        if api_key:
            self._headers["Authorization"] = f"Bearer {api_key}"
        self._conn: http.client.HTTPConnection | None = None

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> LocalizeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # the API ----------------------------------------------------------------------------
    def localize(
        self,
        points: np.ndarray,
        top_n: int = 5,
        preprocess: bool = False,
        *,
        verify: bool | None = None,
        scale: float | None = None,
        kind: str | None = None,
        prior: Any = None,
    ) -> dict[str, Any]:
        """The server's answer for one cloud float [N, 3] (a raw scan with ``preprocess``):
        ``{"matches": [...], "query_kind", "map_kind", "mode", "verified", "pose",
        "verification", "prior", "batch_size", "timings_ms", "model", "index"}``. ``verify``:
        ask for (true) or skip (false) the verification (default: the server's); ``scale``:
        metres per unit of a preprocessed cloud; ``kind``: ``submap``, ``scan`` or ``window`` (a
        scan or window is raw: ``preprocess`` need not be said). ``prior``: where the raw
        scan's sensor is thought to be (a ``Prior`` of
        :mod:`pnvlad_service.localization.verify.prior`, or a mapping with its ``northing``,
        ``easting``, ``yaw_deg`` and optional ``height``, ``radius_m`` and ``run``): the server
        registers the scan to its map near there instead of searching (``mode`` ``prior``); the
        scan is then sent raw."""
        arr = np.asarray(points)
        dtype = "float64" if arr.dtype == np.float64 else "float32"
        body = np.ascontiguousarray(arr, dtype="<f8" if dtype == "float64" else "<f4")
        params: dict[str, Any] = {"top_n": top_n, "dtype": dtype}
        if prior is not None:
            values = prior.to_json() if hasattr(prior, "to_json") else dict(prior)
            for name, value in values.items():
                if value is not None:
                    text = value if isinstance(value, str) else repr(float(value))
                    params[f"prior_{name}"] = text
            if kind is None:
                kind = "scan"
            preprocess = False  # said by the kind
        if kind is None or preprocess:
            params["preprocess"] = str(preprocess).lower()
        if kind is not None:
            params["kind"] = kind
        if verify is not None:
            params["verify"] = str(verify).lower()
        if scale is not None:
            params["scale"] = repr(float(scale))
        query = urllib.parse.urlencode(params)
        return self.call("POST", f"/localize?{query}", body.tobytes(), "application/octet-stream")

    def localize_window(self, window: Any, top_n: int = 5, **options: Any) -> dict[str, Any]:
        """The server's answer for the last stretch of a drive: ``window`` a
        :class:`~pnvlad_service.data.accumulate.WindowAccumulator` the caller feeds its scans
        and poses (the code ``pnvlad data prepare`` lays submaps with), sent as ``kind=window``
        in its newest scan's axes; ``options`` as :meth:`localize` takes them."""
        return self.localize(window.cloud(), top_n, kind="window", **options)

    def window_accumulator(self, window_m: float = 20.0) -> Any:
        """A :class:`~pnvlad_service.data.accumulate.WindowAccumulator` of ``window_m`` metres
        that lays scans as the serving map's windows were laid (its points a scan and range,
        from ``GET /info``): feed it scans and poses, then :meth:`localize_window`."""
        from pnvlad_service.data.accumulate import WindowAccumulator

        return WindowAccumulator.for_map(self.info()["manifest"].get("map"), window_m)

    def ready(self) -> bool:
        """Whether the server answers ``GET /readyz`` with 200 (False when unreachable)."""
        try:
            status, _ = self.send("GET", "/readyz")
        except ServerError:
            return False
        return status == 200

    def info(self) -> dict[str, Any]:
        """``GET /info``: the bundle's manifest, the model and the request limits."""
        return self.call("GET", "/info")

    def reload(self, index: str | None = None, checkpoint: str | None = None) -> Any:
        """``POST /admin/reload`` (the client's ``api_key`` must be the server's admin key):
        serve the bundle at ``index`` (a path on the server; None: the serving bundle's path
        read again) with ``checkpoint`` (None: the serving model). The swap's report, or
        :class:`ServerRefused` (a bundle that fails its checks: 422 naming the file)."""
        body = json.dumps({"index": index, "checkpoint": checkpoint}).encode()
        return self.call("POST", "/admin/reload", body, "application/json")

    # the transport ----------------------------------------------------------------------
    def call(
        self, method: str, path: str, body: bytes | None = None, content_type: str | None = None
    ) -> Any:
        """One request; its JSON answer, or :class:`ServerRefused` / :class:`ServerError`."""
        status, data = self.send(method, path, body, content_type)
        if status >= 400:
            raise self._error(status, data)
        return json.loads(data)

    def send(
        self, method: str, path: str, body: bytes | None = None, content_type: str | None = None
    ) -> tuple[int, bytes]:
        """One request on the kept connection (reopened once if the server closed it while
        idle); ``(status, body)`` whatever the status. :class:`ServerError` if unreachable."""
        headers = dict(self._headers)
        if content_type is not None:
            headers["Content-Type"] = content_type
        for attempt in (0, 1):
            reused = self._conn is not None
            conn = self._connection()
            try:
                conn.request(method, f"{self._prefix}{path}", body=body, headers=headers)
                resp = conn.getresponse()
                return resp.status, resp.read()
            except _RETRY as exc:
                self.close()
                if not reused or attempt:
                    raise ServerError(self.url, f"cannot reach the server: {exc}") from None
            except (OSError, http.client.HTTPException) as exc:
                self.close()
                raise ServerError(self.url, f"cannot reach the server: {exc}") from None
        raise AssertionError("unreachable")  # pragma: no cover

    def _connection(self) -> http.client.HTTPConnection:
        if self._conn is None:
            cls = (
                http.client.HTTPSConnection
                if self._parts.scheme == "https"
                else http.client.HTTPConnection
            )
            self._conn = cls(self._parts.hostname, self._parts.port, timeout=self.timeout)
        return self._conn

    def _error(self, status: int, data: bytes) -> PnvladError:
        try:
            problem = json.loads(data)
            detail = problem.get("detail") or http.client.responses.get(status, "")
        except (ValueError, AttributeError):
            problem, detail = None, http.client.responses.get(status, "")
        message = f"server answered {status}: {detail}"
        if 400 <= status < 500:
            return ServerRefused(self.url, message, status, problem)
        return ServerError(self.url, message, status, problem)
