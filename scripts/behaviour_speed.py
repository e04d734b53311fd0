"""The speed side of a behaviour check: ``POST /localize`` p50 for a submap and for a raw scan,
and the rate of a followed drive, for the code the running python imports, on the fixture of
``scripts/behaviour_snapshot.py``.

Run it with each checkout's own python, back to back on one machine, alternating, and compare
the lines it prints (a ratio is only meaningful within one sitting on one machine)::

    BEFORE/.venv/bin/python scripts/behaviour_speed.py --fixture FIX --rounds 3
    AFTER/.venv/bin/python scripts/behaviour_speed.py --fixture FIX --rounds 3

Each round starts a real ``pnvlad serve`` of each map on 127.0.0.1, sends ``--queries``
sequential requests (after ``--warmup`` unmeasured ones) and takes the wall time of each,
then follows the fixture's bag in this process (``pnvlad localize --rosbag ... --index``) and
reads the rate from its summary line. It prints one JSON line a round and the median of the
rounds.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from behaviour_fixture import child_env
from behaviour_http import Server, npy_bytes, request

NPY = {"content-type": "application/x-npy"}


def _p50_ms(server: Server, path: str, body: bytes, warmup: int, queries: int) -> float:
    for _ in range(warmup):
        status = request(server.url, "POST", path, body, NPY)[0]
        if status != 200:
            raise SystemExit(f"{path}: status {status}")
    times = []
    for _ in range(queries):
        t0 = time.perf_counter()
        request(server.url, "POST", path, body, NPY)
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)


def _follow_rate(fixture: Path, record: dict, work: Path) -> float:
    bag = record["bag"]
    args = [
        sys.executable, "-m", "pnvlad_cli.main", "-q", "localize",
        "--rosbag", str(fixture / bag["path"]), "--cloud-topic", "/points",
        "--pose-topic", "/odom", "--origin", bag["origin"],
        "--index", str(fixture / record["maps"]["keys"]), "--out", str(work / "follow"),
        "--no-plot", "--no-progress",
    ]  # fmt: skip
    done = subprocess.run(args, env=child_env(), capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"follow failed:\n{done.stderr[-2000:]}")
    rate = re.search(r"([0-9.]+) scans/s", done.stdout)
    if rate is None:
        raise SystemExit(f"no rate in the follow's summary:\n{done.stdout[-2000:]}")
    return float(rate.group(1))


def one_round(fixture: Path, record: dict, warmup: int, queries: int) -> dict[str, float]:
    import numpy as np

    submap = npy_bytes(np.load(fixture / "queries" / "submap0.npy"))
    scan = npy_bytes(np.load(fixture / "queries" / "scan0.npy"))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        servers = {
            name: Server(name, fixture / record["maps"][name], {}, work) for name in ("map", "keys")
        }
        try:
            for s in servers.values():
                s.start()
            for s in servers.values():
                s.wait_ready()
            out = {
                "submap_p50_ms": _p50_ms(servers["map"], "/localize", submap, warmup, queries),
                "scan_p50_ms": _p50_ms(
                    servers["keys"], "/localize?preprocess=true&kind=scan", scan, warmup, queries
                ),
            }
        finally:
            for s in servers.values():
                s.stop()
        out["follow_scans_per_s"] = _follow_rate(fixture, record, work)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--fixture", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--queries", type=int, default=40)
    a = ap.parse_args()
    record = json.loads((a.fixture / "fixture.json").read_text())
    rounds = []
    for _ in range(a.rounds):
        rounds.append(one_round(a.fixture, record, a.warmup, a.queries))
        print(json.dumps(rounds[-1]), flush=True)
    median = {k: round(statistics.median(r[k] for r in rounds), 2) for k in rounds[0]}
    print(json.dumps({"code": str(Path(__import__("pnvlad_service").__file__).parent.parent),
                      "median": median}))  # fmt: skip


if __name__ == "__main__":
    main()
