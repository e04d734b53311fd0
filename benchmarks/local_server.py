"""Start `pnvlad serve` on a free loopback port for a benchmark script, and wait until ready.

Shared by load_test.py and fuzz_api.py (run as `python benchmarks/SCRIPT.py`, which puts this
folder on sys.path).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_ready(port: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Poll GET /readyz until it answers 200; exit if the server dies or takes too long."""
    from pnvlad_service.client import LocalizeClient

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit("server exited during start-up")
        with LocalizeClient(f"http://127.0.0.1:{port}", timeout=2) as client:
            if client.ready():
                return
        time.sleep(0.3)
    raise SystemExit("server did not become ready")


def start_server(
    index: Path,
    *,
    checkpoint: Path | None = None,
    env: dict[str, str] | None = None,
) -> tuple[subprocess.Popen, str]:
    """`pnvlad serve --index INDEX` on a free 127.0.0.1 port, ready; returns (process, url)."""
    port = free_port()
    cmd = [sys.executable, "-m", "pnvlad_cli.main", "-q", "serve", "--index", str(index)]
    cmd += ["--port", str(port), "--log-level", "warning"]
    if checkpoint is not None:
        cmd += ["--model", str(checkpoint)]
    proc = subprocess.Popen(cmd, env={**os.environ, **(env or {})})
    wait_ready(port, proc)
    return proc, f"http://127.0.0.1:{port}"
