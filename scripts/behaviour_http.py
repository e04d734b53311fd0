"""The two servers of a behaviour snapshot and the fixed set of requests it sends them
(scripts/behaviour_snapshot.py explains)."""

from __future__ import annotations

import io
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from behaviour_fixture import child_env

ADMIN_KEY = "behaviour-snapshot-admin-key"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Server:
    """A ``pnvlad serve`` of one bundle on 127.0.0.1 (its log in the work folder)."""

    name: str
    bundle: Path
    env: dict[str, str]
    work: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        with open(self.work / f"serve-{self.name}.log", "wb") as log:  # the child keeps its own
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "pnvlad_cli.main",
                    "-q",
                    "serve",
                    "--index",
                    str(self.bundle),
                    "--port",
                    str(self.port),
                    "--log-level",
                    "warning",
                ],
                env=child_env(self.env),
                stdout=log,
                stderr=subprocess.STDOUT,
            )

    def wait_ready(self, timeout_s: float = 240.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc is not None and self.proc.poll() is not None:
                log = (self.work / f"serve-{self.name}.log").read_text()[-3000:]
                raise SystemExit(f"pnvlad serve ({self.name}) exited:\n{log}")
            try:
                if request(self.url, "GET", "/readyz")[0] == 200:
                    return
            except OSError:
                pass
            time.sleep(0.3)
        raise SystemExit(f"pnvlad serve ({self.name}) not ready in {timeout_s:.0f} s")

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def request(
    url: str, method: str, path: str, body: bytes | None = None, headers: dict | None = None
) -> tuple[int, str, bytes]:
    """(status, content type, body) of one request; HTTP errors are answers too."""
    req = urllib.request.Request(url + path, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=300) as res:
            return res.status, res.headers.get("content-type", ""), res.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("content-type", ""), exc.read()


@dataclass
class Ask:
    """One request of the fixed set: ``server`` map or keys; ``json`` a body (numpy arrays
    in it are sent as lists), or ``raw`` (content type, bytes)."""

    name: str
    server: str
    path: str
    method: str = "POST"
    json: Any = None
    raw: tuple[str, bytes] | None = None
    headers: dict[str, str] = field(default_factory=dict)


def encode(value: Any) -> Any:
    """A JSON body with its numpy arrays as lists (float64 values printed exactly)."""
    if hasattr(value, "tolist"):
        return value.astype("float64").tolist()
    if isinstance(value, dict):
        return {k: encode(v) for k, v in value.items()}
    if isinstance(value, list):
        return [encode(v) for v in value]
    return value


def describe(value: Any) -> Any:
    """A body as its record shows it: arrays by shape and dtype, not their values."""
    if hasattr(value, "shape"):
        return f"<{value.dtype} {list(value.shape)}>"
    if isinstance(value, dict):
        return {k: describe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [describe(v) for v in value]
    return value


def npy_bytes(array: Any) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def asks(fixture: Path, q: dict[str, Any]) -> list[Ask]:
    """The fixed set of requests, in the order they are sent: to the submap map (``map``),
    then to the keyframe map (``keys``), then the operations routes and the refusals."""
    import numpy as np

    s = [np.load(fixture / e["file"]) for e in q["submaps"]]
    r = [np.load(fixture / e["file"]) for e in q["scans"]]
    w = np.load(fixture / q["window"]["file"])
    prior = [dict(e["prior"]) for e in q["scans"]]
    return [
        *map_asks(s, w, q["submaps"][1]["scale"]),
        *keys_asks(r, prior, q["prior_run"]),
        *(
            Ask(f"{what}-{srv}", srv, f"/{what}", "GET")
            for srv in ("map", "keys")
            for what in ("info", "readyz", "healthz")
        ),
        *refusals(s, r, w, prior),
    ]


OCTET, NPY = "application/octet-stream", "application/x-npy"


def map_asks(s: list[Any], w: Any, scale: float) -> list[Ask]:
    """Submaps, windows and batches to the submap map."""
    import numpy as np

    f32, stack = s[1].astype("<f4").tobytes(), np.stack(s).astype("<f4")
    window = {"points": w, "preprocess": True, "kind": "window", "top_n": 3}
    return [
        Ask("submap", "map", "/localize", json={"points": s[0], "top_n": 5}),
        Ask("submap-float32", "map", "/localize?top_n=3", raw=(OCTET, f32)),
        Ask("submap-scale", "map", "/localize", json={"points": s[1], "scale": scale}),
        Ask("submap-no-verify", "map", "/localize", json={"points": s[2], "verify": False}),
        Ask("window-npy", "map", "/localize?preprocess=true&kind=window", raw=(NPY, npy_bytes(w))),
        Ask("window-json", "map", "/localize", json=window),
        Ask(
            "batch",
            "map",
            "/localize/batch",
            json={"queries": [{"points": x} for x in s], "top_n": 3},
        ),
        Ask("batch-npy", "map", "/localize/batch?top_n=2", raw=(NPY, npy_bytes(stack))),
    ]


def keys_asks(r: list[Any], prior: list[dict], run: str) -> list[Ask]:
    """Raw scans, with and without a prior, to the keyframe map."""
    params = "&".join(f"prior_{k}={v}" for k, v in prior[1].items())
    far = {**prior[0], "northing": prior[0]["northing"] + 600.0}
    raw = "/localize?preprocess=true&kind=scan"
    return [
        Ask("scan", "keys", "/localize", json={"points": r[0], "preprocess": True, "kind": "scan"}),
        Ask(
            "scan-float64",
            "keys",
            f"{raw}&dtype=float64&top_n=3",
            raw=(OCTET, r[1].astype("<f8").tobytes()),
        ),
        Ask(
            "prior",
            "keys",
            "/localize",
            json={"points": r[0], "preprocess": True, "prior": prior[0]},
        ),
        Ask("prior-params", "keys", f"{raw}&{params}", raw=(OCTET, r[1].astype("<f4").tobytes())),
        Ask(
            "prior-run",
            "keys",
            "/localize",
            json={"points": r[1], "preprocess": True, "prior": {**prior[1], "run": run}},
        ),
        Ask(
            "prior-off-map",
            "keys",
            "/localize",
            json={"points": r[0], "preprocess": True, "prior": far},
        ),
        Ask(
            "batch-scans",
            "keys",
            "/localize/batch",
            json={"queries": [{"points": x, "preprocess": True, "kind": "scan"} for x in r]},
        ),
    ]


def refusals(s: list[Any], r: list[Any], w: Any, prior: list[dict]) -> list[Ask]:
    """Requests each rule refuses, and the admin route without its key or a readable body."""
    one = [[1.0, 2.0, 3.0]]
    garbage = b'{"points": [[0.1, 0.2'
    admin = {"Authorization": f"Bearer {ADMIN_KEY}"}
    raw = {"points": r[0], "preprocess": True}
    return [
        Ask(
            "refuse-prior-with-submap", "map", "/localize", json={"points": s[0], "prior": prior[0]}
        ),
        Ask("refuse-count", "map", "/localize", json={"points": s[0][:100]}),
        Ask("refuse-outside-bound", "map", "/localize", json={"points": s[0] * 2.0}),
        Ask("refuse-top-n", "map", "/localize", json={"points": s[0], "top_n": 0}),
        Ask("refuse-unknown-field", "map", "/localize", json={"points": s[0], "colour": "red"}),
        Ask("refuse-one-point", "map", "/localize", json={"points": one, "preprocess": True}),
        Ask(
            "refuse-batch-one-point",
            "map",
            "/localize/batch",
            json={"queries": [{"points": one, "preprocess": True}]},
        ),
        Ask("refuse-malformed-json", "map", "/localize", raw=("application/json", garbage)),
        Ask("refuse-json-not-utf8", "map", "/localize", raw=("application/json", b"{\xff}")),
        Ask("refuse-media-type", "map", "/localize", raw=("text/plain", b"1 2 3")),
        Ask("refuse-float32-bytes", "map", "/localize", raw=(OCTET, b"\0" * 13)),
        Ask("refuse-not-found", "map", "/nowhere", "GET"),
        Ask("refuse-scale-raw", "keys", "/localize", json={**raw, "scale": 20.0}),
        Ask(
            "refuse-prior-no-verify",
            "keys",
            "/localize",
            json={**raw, "verify": False, "prior": prior[0]},
        ),
        Ask("refuse-kind-not-raw", "keys", "/localize", json={"points": s[0], "kind": "scan"}),
        Ask(
            "refuse-window-on-keyframes",
            "keys",
            "/localize",
            json={"points": w, "preprocess": True, "kind": "window"},
        ),
        Ask(
            "refuse-prior-radius",
            "keys",
            "/localize",
            json={**raw, "prior": {**prior[0], "radius_m": 0.0}},
        ),
        Ask("admin-reload-off", "map", "/admin/reload", json={}),
        Ask("admin-reload-no-key", "keys", "/admin/reload", json={}),
        Ask(
            "admin-reload-wrong-key",
            "keys",
            "/admin/reload",
            json={},
            headers={"Authorization": "Bearer wrong"},
        ),
        Ask(
            "admin-reload-bad-json",
            "keys",
            "/admin/reload",
            headers=admin,
            raw=("application/json", garbage),
        ),
        Ask(
            "admin-reload-not-utf8",
            "keys",
            "/admin/reload",
            headers=admin,
            raw=("application/json", b"{\xff}"),
        ),
        Ask(
            "admin-reload-not-json",
            "keys",
            "/admin/reload",
            headers=admin,
            raw=("text/plain", b"reload please"),
        ),
    ]
