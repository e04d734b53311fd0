"""Does small_gicp's binding release the GIL? A Python thread counts in a loop while the main
thread runs ``small_gicp.preprocess_points`` (one OpenMP thread) on a large cloud; the
counter's rate during the calls, over its idle rate, is the share of the time the GIL was free.
Near 100 %: the binding releases it; near 0: it holds it (docs/results/verify.md,
"the GIL, and verification in a child process").

    python benchmarks/gil_hold.py --points 200000
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
from entry import run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=200_000)
    ap.add_argument("--calls", type=int, default=3)
    args = ap.parse_args()
    import small_gicp

    pts = np.random.default_rng(0).uniform(-40, 40, (args.points, 3))
    stop = threading.Event()
    count = [0]

    def spin() -> None:
        while not stop.is_set():
            count[0] += 1

    thread = threading.Thread(target=spin)
    thread.start()
    time.sleep(0.5)
    start = count[0]
    time.sleep(1.0)
    idle = count[0] - start
    start, t0 = count[0], time.perf_counter()
    for _ in range(args.calls):
        small_gicp.preprocess_points(pts, 0.5, num_neighbors=10, num_threads=1)
    seconds = time.perf_counter() - t0
    during = (count[0] - start) / seconds
    stop.set()
    thread.join()
    print(
        f"counter: {idle:,.0f}/s idle, {during:,.0f}/s during {args.calls} calls "
        f"({seconds:.2f} s): the GIL was free {100 * during / idle:.1f} % of the time"
    )


if __name__ == "__main__":
    run(main)
