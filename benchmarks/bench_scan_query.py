"""A raw single scan to a verified answer through `POST /localize`, stage by stage (issue #34).

Starts `pnvlad serve --index MAP` on loopback (a keyframe map with geometry, so that answers are
verified) and sends one raw scan at a time (``kind=scan``: the server runs G, embeds, searches
and verifies): prints the p50 of the whole request as the client saw it and of each stage the
server reports (parse, G, queue, embed, search, verify), each stage's share, the points a scan
had, and how many answers were verified and within 25 m of the truth.

The scans are those of a run the map left out, at its query places (``--run``: a run folder of
a ``pnvlad synth`` tree), cast again with a denser sensor (``--beams``, ``--columns``; the
default, 64 x 2,600 rays, gives about 120,000 points, as a KITTI HDL-64E scan has) from the
very poses of the tree's raw scans, or the tree's own raw scans (``--columns 0``).

It also times what an accumulated query adds a scan (``--window``): laying the last 20 m of
scans together (:class:`~pnvlad_service.data.accumulate.WindowAccumulator`) and running G on
the window instead of one scan, in this process.

    python benchmarks/bench_scan_query.py --index MAP --run B/business/RUN --count 40
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from entry import run
from local_server import start_server

from pnvlad_service.client import LocalizeClient
from pnvlad_service.data.scans import read_raw_scans

STAGES = ("parse", "preprocess", "queue", "embed", "search", "verify")


def dense_scans(run_dir: Path, count: int, beams: int, columns: int) -> list[tuple]:
    """(points float32 [N, 3], true pose [4, 4]) of up to ``count`` query places of the run: the
    tree's raw scans, or (``columns`` > 0) the same places cast again with a denser sensor."""
    scans = read_raw_scans(run_dir)
    step = max(len(scans) // count, 1)
    chosen = scans[::step][:count]
    if columns <= 0:
        from pnvlad_service.io.readers import read_points

        return [(read_points(s.path, "kitti"), s.true_pose) for s in chosen]
    from pnvlad_service.synth.generate import simulated_drive
    from pnvlad_service.synth.windows import drives_of

    root, area, name = run_dir.parent.parent, run_dir.parent.name, run_dir.name
    spec, a, k, seed = drives_of(root)[(area, name)]
    lidar = spec.lidar.model_copy(update={"beams": beams, "columns": columns})
    drive = simulated_drive(spec.model_copy(update={"lidar": lidar}), a, k, seed)
    index = {int(t): i for i, t in enumerate(drive.timestamps)}
    return [(drive.scan(index[s.timestamp]), s.true_pose) for s in chosen]


def window_cost(run_dir: Path, count: int) -> None:
    """What an accumulated 20 m query costs a scan beyond a single scan's G, in this process."""
    from pnvlad_service.data.accumulate import WindowAccumulator
    from pnvlad_service.preprocess.filter_g import GConfig, apply_g, scan_config
    from pnvlad_service.synth.generate import simulated_drive
    from pnvlad_service.synth.windows import drives_of

    root, area, name = run_dir.parent.parent, run_dir.parent.name, run_dir.name
    drive = simulated_drive(*drives_of(root)[(area, name)])
    # laid as the tree's submap windows were (their points a scan, as a served map says)
    from pnvlad_service.data.run_folder import recorded_accumulation

    acc = WindowAccumulator.laid_as(recorded_accumulation(run_dir, "pointcloud_20m"), 20.0)
    add_s, cloud_s, g_window, g_scan, points = [], [], [], [], []
    first = max(0, min(100, len(drive) - 8 - count))
    for i in range(first, min(len(drive), first + 8 + count)):
        pts = drive.scan(i)
        t0 = time.perf_counter()
        acc.add(pts, drive.poses[i])
        add_s.append(time.perf_counter() - t0)
        if acc.span_m < 15.0:
            continue
        t0 = time.perf_counter()
        cloud = acc.cloud()
        cloud_s.append(time.perf_counter() - t0)
        points.append(len(cloud))
        t0 = time.perf_counter()
        apply_g(cloud, GConfig())
        g_window.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        apply_g(pts, scan_config())
        g_scan.append(time.perf_counter() - t0)
    ms = lambda v: 1000 * float(np.median(v))  # noqa: E731
    extra = ms(add_s) + ms(cloud_s) + ms(g_window) - ms(g_scan)
    print(
        f"accumulated query (20 m, {int(np.median(points)):,} points): add {ms(add_s):.1f} ms a "
        f"scan, laying the window {ms(cloud_s):.1f} ms, G on it {ms(g_window):.1f} ms against "
        f"{ms(g_scan):.1f} ms on one scan: {extra:+.1f} ms a query"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--index", type=Path, required=True, help="a keyframe bundle with geometry")
    ap.add_argument("--model", type=Path, help="default: the one the bundle records")
    ap.add_argument("--run", type=Path, required=True, help="a synth run folder the map left out")
    ap.add_argument("--count", type=int, default=40, help="scans sent (after 3 to warm up)")
    ap.add_argument("--beams", type=int, default=64)
    ap.add_argument("--columns", type=int, default=2600, help="0: the tree's raw scans")
    ap.add_argument("--window", action="store_true", help="also time an accumulated query")
    args = ap.parse_args()

    scans = dense_scans(args.run, args.count + 3, args.beams, args.columns)
    proc, url = start_server(args.index, checkpoint=args.model)
    stages: dict[str, list[float]] = {s: [] for s in (*STAGES, "total")}
    wall: list[float] = []
    verified = within = 0
    try:
        with LocalizeClient(url, timeout=60) as client:
            for k, (pts, true) in enumerate(scans):
                body = np.ascontiguousarray(pts, dtype=np.float32)
                t0 = time.perf_counter()
                answer = client.localize(body, 5, kind="scan")
                elapsed = time.perf_counter() - t0
                if k < 3:
                    continue  # warm-up
                wall.append(elapsed)
                for s in stages:
                    stages[s].append(answer["timings_ms"][s])
                top = answer["matches"][0]
                within += (
                    math.hypot(top["northing"] - true[1, 3], top["easting"] - true[0, 3]) <= 25
                )
                verified += bool(answer.get("verified"))
    finally:
        proc.terminate()
        proc.wait(30)
    n = len(wall)
    p50 = 1000 * float(np.median(wall))
    points = int(np.median([len(p) for p, _ in scans]))
    print(f"{n} raw scans of {points:,} points (median) through POST /localize, one at a time:")
    p90 = 1000 * float(np.percentile(wall, 90))
    print(f"  p50 {p50:.1f} ms a request as the client saw it (p90 {p90:.1f})")
    total = float(np.median(stages["total"]))
    for s in STAGES:
        v = float(np.median(stages[s]))
        print(f"  {s:<10} {v:7.1f} ms  {100 * v / p50:5.1f} %")
    print(f"  server's own total {total:.1f} ms; HTTP and the client {p50 - total:.1f} ms")
    print(f"  {verified} of {n} verified, {within} of {n} with the top-1 within 25 m")
    if args.window:
        window_cost(args.run, 12)
    return 0


if __name__ == "__main__":
    run(main)
