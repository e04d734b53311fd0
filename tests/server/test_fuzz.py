"""The HTTP contract, fuzzed: Schemathesis (an independent OpenAPI fuzzer) against a real
`pnvlad serve` on 127.0.0.1 with a small map that carries geometry, every check on, a bounded
number of examples per route; no failure allowed. The three rules OpenAPI cannot state are the
hooks' (tests/server/fuzz_hooks.py, each said in words there and in the document). A second,
smaller run against a server with an API key checks the bearer scheme the document declares.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.index.helpers import free_port, make_world
from tests.server.test_app import start_server, stop_server

pytest.importorskip("schemathesis")

ROOT = Path(__file__).resolve().parents[2]
KEY = "fuzz-key"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_world(tmp_path_factory.mktemp("fuzz"), frames=True)["bundle"]


@pytest.fixture()
def server(request: pytest.FixtureRequest, bundle: Path) -> Iterator[str]:
    port = free_port()
    env = {"PNVLAD_MAX_BODY_BYTES": str(8 * 1024 * 1024), **getattr(request, "param", {})}
    proc = start_server(bundle, port, env=env)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


def fuzz(url: str, examples: int, *extra: str) -> tuple[subprocess.CompletedProcess, dict]:
    """``st run`` on the server's document, every check, ``examples`` per route; the run and
    its JSON report."""
    report = Path(os.environ.get("TMPDIR", "/tmp")) / f"fuzz-{os.getpid()}-{time.time_ns()}.json"
    cmd = [
        sys.executable, "-m", "schemathesis.cli", "run", f"{url}/openapi.json",
        "--checks", "all", "--max-examples", str(examples), "--seed", "1",
        "--generation-deterministic", "--request-timeout", "60", "--workers", "1",
        "--report", "json", "--report-json-path", str(report), *extra,
    ]  # fmt: skip
    env = {
        **os.environ,
        "SCHEMATHESIS_HOOKS": "tests.server.fuzz_hooks",
        "PYTHONPATH": str(ROOT),
        "NO_COLOR": "1",
    }
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    doc = json.loads(report.read_text()) if report.is_file() else {}
    report.unlink(missing_ok=True)
    return out, doc


def cases(stdout: str) -> int:
    """The test cases the run generated (its summary line)."""
    found = re.search(r"(\d+) generated", stdout)
    return int(found.group(1)) if found else 0


def test_the_document_holds_against_a_fuzzer(server: str) -> None:
    t0 = time.monotonic()
    out, _ = fuzz(server, 6)
    took = time.monotonic() - t0
    print(f"schemathesis: {cases(out.stdout)} cases in {took:.1f} s")
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
    assert "No issues found" in out.stdout or " passed" in out.stdout, out.stdout[-3000:]
    assert cases(out.stdout) >= 100  # the run really generated requests


@pytest.mark.parametrize("server", [{"PNVLAD_API_KEY": KEY}], indirect=True)
def test_the_bearer_scheme_holds_against_a_fuzzer(server: str) -> None:
    """With a key the document declares the bearer scheme on every route but the probes:
    without the header, or with a wrong token, a client gets the 401 the document says."""
    # One route of each guard (the probes open, /info and /localize the API key's, the admin
    # route the admin key's or the API key's) is enough: the guards are the routers'.
    only = ["--include-path-regex", "^/(healthz|info|localize|admin/reload)$"]
    t0 = time.monotonic()
    out, _ = fuzz(server, 3, "--header", f"Authorization: Bearer {KEY}", *only)
    print(f"schemathesis with a key: {cases(out.stdout)} cases in {time.monotonic() - t0:.1f} s")
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
    assert cases(out.stdout) >= 30
