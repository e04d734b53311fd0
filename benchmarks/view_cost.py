"""What the live view and its MCAP cost a follow: the same bag followed with and without
``--foxglove`` and ``--mcap``, interleaved (plain, view, plain, view, ...), repeated; prints
each pair's rates (scans/s, the follow's own summary line), their ratio, and the median and
spread of the ratios.

    python benchmarks/view_cost.py --bag held --index map.index --origin 5734500.0,619000.0 \
        --repeats 5 --out out/view_cost

Each follow is its own ``pnvlad localize`` process (the bag opened, the bundle loaded), so the
figure is the command's as a user runs it; the live view has no client connected (its MCAP is
written: every message is encoded either way).
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from pathlib import Path


def follow(args: argparse.Namespace, out: Path, view: bool) -> float:
    """One follow's scans/s (its summary line)."""
    cmd = [
        sys.executable, "-m", "pnvlad_cli.main", "-q", "localize", "--rosbag", str(args.bag),
        "--cloud-topic", "/points", "--pose-topic", "/odom", "--truth-topic", "/ground_truth",
        "--origin", args.origin, "--index", str(args.index), "--out", str(out), "--no-plot",
        "--no-progress",
    ]  # fmt: skip
    if view:
        cmd += ["--foxglove", "127.0.0.1:0", "--mcap", f"{out}.mcap"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"follow failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    rate = re.search(r"\(([0-9.]+) scans/s", done.stdout)
    if rate is None:
        raise SystemExit(f"no rate in the follow's summary:\n{done.stdout[-2000:]}")
    return float(rate.group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, required=True, help="a ROS bag (make_rosbag.py)")
    parser.add_argument("--index", type=Path, required=True, help="the map's bundle")
    parser.add_argument("--origin", required=True, help="NORTHING,EASTING of the bag's poses")
    parser.add_argument("--repeats", type=int, default=5, help="pairs of follows")
    parser.add_argument("--out", type=Path, required=True, help="folder for the outputs")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    ratios = []
    for k in range(args.repeats):
        first_view = k % 2 == 1  # alternate which goes first
        rates = {}
        for view in (first_view, not first_view):
            name = f"{'view' if view else 'plain'}{k}"
            for old in args.out.glob(f"{name}*"):
                old.unlink()
            rates[view] = follow(args, args.out / name, view)
        ratio = rates[True] / rates[False]
        ratios.append(ratio)
        print(f"pair {k}: plain {rates[False]:.2f} scans/s, view + MCAP {rates[True]:.2f} "
              f"scans/s, ratio {ratio:.3f}", flush=True)  # fmt: skip
    spread = f"{min(ratios):.3f}-{max(ratios):.3f}"
    print(f"view + MCAP / plain: median {statistics.median(ratios):.3f} (range {spread}, "
          f"{len(ratios)} pairs)")  # fmt: skip


if __name__ == "__main__":
    main()
