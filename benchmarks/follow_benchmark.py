"""Real time: a bag followed scan by scan through `pnvlad serve` on the same machine (#36).

Starts `pnvlad serve --index MAP` on loopback (its verification process included, as a robot's
server runs) and follows the bag with `pnvlad localize --rosbag BAG --url ...` (the command a
user runs: every scan, searching until a fix, then tracking by registration near the
prediction). Prints the command's own lines (the stages' mean times when searching and when
tracking, the summary), then what a real-time robot asks of it: scans processed a second
against the sensor's rate (``--rate``, 10 Hz), the p50 / p90 / p99 of a scan's time (reading
it, odometry, the request), the share of scans done within one sensor period, and the CPU the
server (with its children) and this process spent a scan.

    python benchmarks/follow_benchmark.py --bag held.bag --index map.index \\
        --origin 5734500.0,619000.0 --out out/follow
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

import numpy as np
from entry import run
from local_server import start_server

from pnvlad_service.extras import require


def tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` and every live descendant (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    parents: dict[int, int] = {}
    cpu: dict[int, float] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(entry)] = int(fields[1])
        cpu[int(entry)] = (int(fields[11]) + int(fields[12])) / tick
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        total += cpu.get(p, 0.0)
        todo += [c for c, parent in parents.items() if parent == p]
    return total


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", type=Path, required=True, help="a ROS bag (make_rosbag.py writes one)")
    ap.add_argument("--index", type=Path, required=True, help="a keyframe map with geometry")
    ap.add_argument("--origin", required=True, help="NORTHING,EASTING of the pose frame")
    ap.add_argument("--out", type=Path, required=True, help="OUT.csv and OUT.png")
    ap.add_argument("--cloud-topic", default="/points")
    ap.add_argument("--pose-topic", default="/odom", help="odometry ('' for KISS-ICP)")
    ap.add_argument("--truth-topic", default="/ground_truth", help="'' for none")
    ap.add_argument("--rate", type=float, default=10.0, help="the sensor's scans a second")
    args = ap.parse_args()
    require("rosbags", "rosbags", "rosbag", "Replaying bags")

    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.localization.drive.rows import read_rows

    proc, url = start_server(args.index)
    try:
        cmd = ["localize", "--rosbag", str(args.bag), "--cloud-topic", args.cloud_topic,
               "--origin", args.origin, "--url", url, "--map", str(args.index),
               "--out", str(args.out), "--no-progress"]  # fmt: skip
        if args.pose_topic:
            cmd += ["--pose-topic", args.pose_topic]
        if args.truth_topic:
            cmd += ["--truth-topic", args.truth_topic]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        server0, here0 = tree_cpu_s(proc.pid), resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        res = CliRunner().invoke(app, cmd)
        wall = time.perf_counter() - t0
        server_cpu = tree_cpu_s(proc.pid) - server0
        here1 = resource.getrusage(resource.RUSAGE_SELF)
    finally:
        proc.terminate()
        proc.wait(30)
    if res.exit_code != 0:
        raise SystemExit(f"the follow failed:\n{res.output}")
    print(res.stdout.strip())
    rows = read_rows(f"{args.out}.csv")
    per_scan = np.array([r.read_ms + r.odometry_ms + r.step_ms for r in rows])
    period_ms = 1000.0 / args.rate
    here_cpu = (here1.ru_utime - here0.ru_utime) + (here1.ru_stime - here0.ru_stime)
    n = len(rows)
    print(
        f"real time: {n} scans in {wall:.1f} s (the command, bag opening included): "
        f"{n / wall:.1f} scans/s against the sensor's {args.rate:g}; a scan's time p50 "
        f"{np.percentile(per_scan, 50):.1f} ms, p90 {np.percentile(per_scan, 90):.1f} ms, p99 "
        f"{np.percentile(per_scan, 99):.1f} ms; {100 * np.mean(per_scan <= period_ms):.1f} % "
        f"within {period_ms:.0f} ms"
    )
    print(
        f"CPU a scan: server {1000 * server_cpu / n:.1f} ms (with its verification process), "
        f"this process {1000 * here_cpu / n:.1f} ms; {os.cpu_count()} cores"
    )
    return 0


if __name__ == "__main__":
    run(main)
