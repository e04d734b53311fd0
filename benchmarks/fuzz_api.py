"""Schema-based fuzzing of the HTTP API with schemathesis (bounded), expecting zero 5xx.

Starts `pnvlad serve` on loopback on the given bundle (or uses --url), then runs
`schemathesis run` against /openapi.json with every check (server errors, status codes,
content types and response schemas as documented), at most --max-examples cases per
operation. Needs `pip install schemathesis` (a dev tool, not a runtime dependency).

`positive_data_acceptance` is excluded by default: two rules cannot be written in OpenAPI
and are rightly answered 422 for schema-valid data: a binary body must be a whole number of
xyz triples (12 or 24 bytes each), and the filter G refuses a raw scan that ground removal
empties. Every other check runs, and a 5xx always fails.

    python benchmarks/fuzz_api.py --index demo/map.index --max-examples 100
"""

from __future__ import annotations

import argparse
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
    ap.add_argument("--exclude-checks", default="positive_data_acceptance")
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
        rc = subprocess.call(cmd)
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(20)
    return rc


if __name__ == "__main__":
    run(main)
