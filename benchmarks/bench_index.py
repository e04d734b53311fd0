"""Index scale benchmark: build time, memory and search latency of FAISS index keys.

The database is N random unit vectors (float32, d = 256 by default); the queries are database
vectors plus Gaussian noise (a revisit of a mapped place), renormalised. For each N and key:
build (train + add) time, index size in memory (serialised bytes) and the process's peak RSS
growth, single-query search latency p50/p99 over --queries queries, and recall@1 against exact
search. Bounded: --queries (default 200) and the sizes given.

    python benchmarks/bench_index.py                          # 1e4, 1e5, 1e6 x Flat, HNSW32, IVF-PQ
    python benchmarks/bench_index.py --sizes 10000 100000 --keys Flat HNSW32
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument(
        "--keys",
        nargs="+",
        default=["Flat", "HNSW32", "IVF-PQ"],
        help="FAISS keys; 'IVF-PQ' means IVF{ivf_lists(N)},PQ32",
    )
    ap.add_argument("--dim", type=int, default=256)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--noise", type=float, default=0.3, help="Query noise norm (unit vectors).")
    ap.add_argument("--threads", type=int, default=None, help="FAISS OpenMP threads.")
    ap.add_argument("--json", type=str, default=None, help="Also write the rows here.")
    args = ap.parse_args()

    import faiss

    from pnvlad_service.index.keys import (
        apply_search_params,
        default_search_params,
        ivf_lists,
        make_index,
    )

    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    rows = []
    print(
        f"{'N':>9} {'key':<18} {'build s':>8} {'index MB':>9} {'RSS+ MB':>8} "
        f"{'p50 ms':>8} {'p99 ms':>8} {'recall@1':>8}"
    )
    for n in args.sizes:
        rng = np.random.default_rng(n)
        xb = unit(rng.standard_normal((n, args.dim), dtype=np.float32))
        pick = rng.choice(n, args.queries, replace=False)
        noise = rng.standard_normal((args.queries, args.dim), dtype=np.float32)
        xq = unit(xb[pick] + args.noise * noise / np.sqrt(args.dim))
        exact = faiss.IndexFlatL2(args.dim)
        exact.add(xb)
        _, gt = exact.search(xq, 1)
        del exact
        for key in args.keys:
            real = f"IVF{ivf_lists(n)},PQ32" if key == "IVF-PQ" else key
            rss0 = rss_mb()
            t0 = time.perf_counter()
            index = make_index(xb, real)  # what `pnvlad index build` does
            build = time.perf_counter() - t0
            apply_search_params(index, default_search_params(real))
            size_mb = len(faiss.serialize_index(index)) / 2**20
            rss_grow = rss_mb() - rss0
            lat = []
            found = np.empty(args.queries, dtype=np.int64)
            for i in range(args.queries):
                t = time.perf_counter()
                _, ids = index.search(xq[i : i + 1], 1)
                lat.append(time.perf_counter() - t)
                found[i] = ids[0, 0]
            p50, p99 = np.percentile(np.array(lat) * 1000, [50, 99])
            recall = float((found == gt[:, 0]).mean())
            row = {
                "n": n,
                "key": real,
                "build_s": round(build, 2),
                "index_mb": round(size_mb, 1),
                "rss_growth_mb": round(rss_grow, 1),
                "p50_ms": round(float(p50), 3),
                "p99_ms": round(float(p99), 3),
                "recall_at_1": recall,
                "params": default_search_params(real),
            }
            rows.append(row)
            print(
                f"{n:>9} {real:<18} {build:>8.2f} {size_mb:>9.1f} {rss_grow:>8.1f} "
                f"{p50:>8.3f} {p99:>8.3f} {recall:>8.3f}",
                flush=True,
            )
            del index
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MB; faiss threads {faiss.omp_get_max_threads()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
