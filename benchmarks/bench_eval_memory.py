"""Peak memory of an Oxford-sized evaluation: descriptors in memory, never all the clouds.

Makes a benchmark tree of random submaps in a temporary folder (23 runs; 9,492 database and
about 3,030 query submaps, as the Oxford evaluation), evaluates a randomly initialised compact
model on it with the same code path as ``pnvlad eval`` (splits built from the tree, every unique
submap embedded once, FAISS search per run pair) and prints the peak resident set size
(``resource.getrusage``) and timings.

To keep the temporary tree small and quick to write, ``--distinct`` random submaps are written
and the rest are hard links to them (each path is still read and embedded separately).

    python benchmarks/bench_eval_memory.py                 # Oxford-sized, compact model
    python benchmarks/bench_eval_memory.py --runs 4 --db-per-run 100   # a quick look
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from entry import run


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def make_tree(root: Path, runs: int, db_per_run: int, distinct: int, seed: int = 0) -> int:
    """Runs along the same 4 km route, a submap every ~9.7 m; queries: the middle third."""
    from pnvlad_service.data import splits
    from pnvlad_service.data import tree as benchmark

    rng = np.random.default_rng(seed)
    pool = root / ".pool"
    pool.mkdir(parents=True)
    for k in range(distinct):
        pts = rng.uniform(-1, 1, (4096, 3))
        pts.astype("<f8").tofile(pool / f"{k}.bin")
    length = db_per_run * 9.7
    base_n, base_e = 5_735_000.0, 620_000.0
    files = 0
    for r in range(runs):
        run = root / "oxford" / f"2015-01-{r + 1:02d}-00-00-00"
        folder = run / "pointcloud_20m"
        folder.mkdir(parents=True)
        n = db_per_run + int(rng.integers(-3, 4))
        north = np.sort(rng.uniform(0, length, n))
        rows = []
        for k in range(n):
            ts = 1_420_000_000_000_000 + r * 10**10 + k
            os.link(pool / f"{files % distinct}.bin", folder / f"{ts}.bin")
            files += 1
            rows.append((ts, base_n + north[k], base_e + rng.normal(scale=2.0)))
        benchmark.write_locations_csv(run / "pointcloud_locations_20m.csv", rows)
    # one test region over the middle third of the route: about a third of the submaps
    reg = splits.TestRegions(((base_n + length / 2, base_e),), length / 6)
    splits.save_regions(root / "oxford" / splits.REGIONS_FILE, reg)
    return files


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=23)
    ap.add_argument("--db-per-run", type=int, default=413, help="9,492 / 23 = 412.7")
    ap.add_argument("--distinct", type=int, default=256, help="distinct random submaps on disk")
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument(
        "--num-points",
        type=int,
        default=4096,
        help="points a cloud the model sees (fewer: a cheaper network, same counts)",
    )
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import torch

    from pnvlad_service.data.dataset import load_eval_runs
    from pnvlad_service.evaluation.evaluate import evaluate_runs
    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.inference import Encoder

    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"after imports: peak RSS {peak_rss_mib():.0f} MiB")
    with tempfile.TemporaryDirectory(prefix="pnvlad-bench-") as tmp:
        root = Path(tmp)
        t0 = time.monotonic()
        n = make_tree(root, args.runs, args.db_per_run, args.distinct)
        print(f"tree: {n} submap paths in {time.monotonic() - t0:.1f} s")
        runs = load_eval_runs(root)
        n_db = sum(len(r.db_paths) for r in runs)
        n_q = sum(len(r.query_paths) for r in runs)
        print(f"evaluation set: {len(runs)} runs, {n_db} database, {n_q} queries")
        torch.manual_seed(0)
        cfg = ModelConfig.compact(num_points=args.num_points)
        # the encoder `pnvlad eval --checkpoint` uses: batch norm folded, inference mode
        enc = Encoder(build_model(cfg), cfg, batch_size=32)
        t1 = time.monotonic()
        rep = evaluate_runs(enc.embed, runs, cfg.num_points, workers=args.workers, progress=True)
        dt = time.monotonic() - t1
        rate = rep["n_unique_submaps"] / rep["seconds_embedding"]
        print(
            f"eval: {rep['n_pairs']} run pairs, {rep['n_unique_submaps']} submaps embedded in "
            f"{rep['seconds_embedding']:.1f} s ({rate:.0f} submaps/s), total {dt:.1f} s; "
            f"recall@1 {rep['recall_at_1']:.2f} (random model)"
        )
    print(f"peak RSS: {peak_rss_mib():.0f} MiB (limit 2048 MiB)")


if __name__ == "__main__":
    run(main)
