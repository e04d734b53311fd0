"""Schema-based fuzzing of the HTTP API with schemathesis (bounded), expecting zero 5xx.

Starts `pnvlad serve` on loopback on the given bundle (or uses --url), then runs
`schemathesis run` against /openapi.json with every check (server errors, status codes,
content types and response schemas as documented), at most --max-examples cases per
operation. Needs `pip install schemathesis` (a dev tool, not a runtime dependency).

Every check runs. The rules OpenAPI cannot state (the query parameters of a binary body go
together, a binary body is whole xyz triples, a reload names paths on the server's disk, the
filter G refuses a raw scan that ground removal empties) are the hooks of
tests/server/fuzz_hooks.py, which the test suite's own run (tests/server/test_fuzz.py) uses too.

    python benchmarks/fuzz_api.py --index demo/map.index --max-examples 100
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
from pathlib import Path

from entry import run
from local_server import start_server

from pnvlad_service.errors import MissingDependencyError


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--index", type=Path, help="Bundle to serve.")
    ap.add_argument("--url", help="A running server instead (loopback).")
    ap.add_argument("--max-examples", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--checks", default="all")
    ap.add_argument("--exclude-checks", default="")
    args = ap.parse_args()
    st = shutil.which("st") or shutil.which("schemathesis")
    if st is None:  # its command, not its module: it runs as a child process
        raise MissingDependencyError("schemathesis", "fuzz", "Fuzzing the HTTP API")
    proc = None
    url = args.url
    if url is None:
        if args.index is None:
            ap.error("give --index or --url")
        proc, url = start_server(args.index, env={"PNVLAD_MAX_BODY_BYTES": str(8 * 1024 * 1024)})
    try:
        cmd = [
            st,
            "run",
            f"{url}/openapi.json",
            "--checks",
            args.checks,
            "--max-examples",
            str(args.max_examples),
            "--seed",
            str(args.seed),
            "--request-timeout",
            "60",
            "--generation-deterministic",
        ]
        if args.exclude_checks:
            cmd += ["--exclude-checks", args.exclude_checks]
        print(" ".join(cmd), flush=True)
        root = Path(__file__).resolve().parents[1]
        env = {
            **os.environ,
            "SCHEMATHESIS_HOOKS": "tests.server.fuzz_hooks",
            "PYTHONPATH": str(root),
        }
        rc = subprocess.call(cmd, cwd=root, env=env)
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(20)
    return rc


if __name__ == "__main__":
    run(main)
