"""Per-area recall of the training-free baseline descriptor on a benchmark tree.

For every evaluation set of the splits (one per area of a ``pnvlad synth`` tree): read each
run's database submaps once, describe them with ``pnvlad_service.evaluation.baseline``
(a Scan-Context style polar height grid), search every ordered run pair with FAISS
(``IndexFlatL2``, exact, 25 neighbours), score with ``metrics.pair_recall_from_neighbours``
and average over pairs as the published evaluation does. Prints a markdown table (area, runs,
database submaps, queries, recall@1, recall@1%) and, with --json, writes the figures.

    python benchmarks/baseline_recall.py data/bench                 # splits: data/bench/splits.json
    python benchmarks/baseline_recall.py data/bench --json base.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from entry import run


def read_submaps(root: Path, files: list[str]) -> np.ndarray:
    """float64 [B, 4096, 3]: the submaps ``files`` (paths relative to ``root``)."""
    from pnvlad_service.io.readers import read_points

    return np.stack([read_points(root / f, "benchmark") for f in files])


def area_recall(root: Path, es: object) -> dict:
    """Recall@1 and recall@1% (percent) of one ``EvaluationSet``, averaged over run pairs."""
    import faiss

    from pnvlad_service.evaluation import baseline
    from pnvlad_service.evaluation.metrics import average_pairs, pair_recall_from_neighbours

    db_desc = [baseline.describe(read_submaps(root, d.files)) for d in es.database]
    per_pair, skipped = [], []
    for j in range(len(es.queries)):
        qi = es.query_db_index(j)
        assert (qi >= 0).all(), "a query is not in its run's database"
        q_desc = db_desc[j][qi]  # queries are database submaps of their own run
        for i, db in enumerate(db_desc):
            if i == j:
                continue
            index = faiss.IndexFlatL2(db.shape[1])
            index.add(db)
            _, nn = index.search(q_desc, min(25, len(db)))
            pr = pair_recall_from_neighbours(nn, es.truth[j][i], len(db), db=i, query=j)
            if pr is None:
                skipped.append((i, j))
            else:
                per_pair.append(pr)
    res = average_pairs(per_pair, skipped)
    return {
        "area": es.name,
        "runs": len(es.runs),
        "database": int(sum(len(d) for d in es.database)),
        "queries": int(es.n_queries()),
        "pairs": len(per_pair),
        "recall_at_1": round(res.recall_at_1, 2),
        "recall_at_1pct": round(res.recall_at_1pct, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="benchmark tree (e.g. the output of pnvlad synth)")
    ap.add_argument("--splits", type=Path, help="splits JSON (default ROOT/splits.json)")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = ap.parse_args()
    from pnvlad_service.data.splits import load_splits

    splits = load_splits(args.splits or args.root / "splits.json")
    started = time.perf_counter()
    rows = []
    for es in splits.evaluation.values():
        # paths in the splits are relative to the dataset folder's parent (the tree root)
        rows.append(area_recall(args.root, es))
    print("| area | runs | database submaps | queries | recall@1 (%) | recall@1% (%) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['area']} | {r['runs']} | {r['database']} | {r['queries']} | "
            f"{r['recall_at_1']:.1f} | {r['recall_at_1pct']:.1f} |"
        )
    if len(rows) > 1:
        print(
            f"| mean | | {sum(r['database'] for r in rows)} | {sum(r['queries'] for r in rows)} | "
            f"{np.mean([r['recall_at_1'] for r in rows]):.1f} | "
            f"{np.mean([r['recall_at_1pct'] for r in rows]):.1f} |"
        )
    print(f"({time.perf_counter() - started:.1f} s)")
    if args.json:
        args.json.write_text(json.dumps({"areas": rows}, indent=1) + "\n")


if __name__ == "__main__":
    run(main)
