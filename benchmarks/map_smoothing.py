"""Smoothing the map along its drives, swept: recall@1 / recall@1% at each radius and weight.

    python benchmarks/map_smoothing.py -m MODEL --root TREE --splits SPLITS \
        [--radius 15 --radius 25 ...] [--weight 0.3 --weight 0.5 ...] [--db-layout train]
        [--joint-map] [--num-points N] [--json out.json]

Embeds the evaluation runs of SPLITS once with MODEL (as ``pnvlad eval``), then evaluates the
queries against each run's database smoothed along the run (``pnvlad index build --smooth R
--smooth-weight W``; pnvlad_service/index/smoothing.py) for every radius and weight given, and
without smoothing. Printed per setting: recall@1 and recall@1% over all run pairs, each area's
recall@1, and the change against no smoothing.

``--db-layout train``: each run's database is its training-layout submaps (every 10 m, the
published ``pointcloud_20m_10overlap``) instead of its test-layout ones (every 20 m), the truth
recomputed at 25 m: whether a setting holds on a map twice as dense.

``--joint-map``: the map a service holds instead of the benchmark's pairs: each run's queries
against one database of every other run of its area (right: a map entry within 25 m), the map
smoothed along each drive and across the drives (``pnvlad index build --smooth R
--smooth-across-drives``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import run

from pnvlad_service.data.dataset import load_eval_runs
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.evaluation.evaluate import (
    embed_runs,
    evaluate_embedded,
    exact_search,
    model_encoder,
    smooth_databases,
)
from pnvlad_service.index.smoothing import Smoothing

TRUTH_M = 25.0


def train_layout_databases(root: Path, runs: list) -> list:
    """``runs`` with each database replaced by the run's training-layout submaps and the truth
    recomputed (database submaps within 25 m of each query, in every other run)."""
    tree = BenchmarkTree(root)
    by_run = {
        (dataset, run): tree.submaps(dataset, run, "train")
        for dataset in tree.datasets
        for run in tree.runs(dataset)
    }
    out = []
    for r in runs:
        name = r.name.split("/")[-1]
        subs = by_run.get((r.area, name))
        if not subs:
            raise SystemExit(f"run {r.name}: no training-layout submaps in {root}")
        out.append(
            replace(
                r,
                db_paths=[root / s.path for s in subs],
                db_positions=np.array([[s.northing, s.easting] for s in subs]),
            )
        )
    for j, q in enumerate(out):
        truth = []
        for pos in q.query_positions:
            t = {}
            for i, d in enumerate(out):
                if i != j and d.area == q.area:
                    near = np.flatnonzero(np.linalg.norm(d.db_positions - pos, axis=1) <= TRUTH_M)
                    if len(near):
                        t[i] = near.astype(np.int64)
            truth.append(t)
        out[j] = replace(q, truth=truth)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-m", "--model", required=True)
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--splits", type=Path, required=True)
    ap.add_argument("--radius", type=float, action="append", default=None)
    ap.add_argument("--weight", type=float, action="append", default=None)
    ap.add_argument("--db-layout", choices=("test", "train"), default="test")
    ap.add_argument("--joint-map", action="store_true")
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--num-points", type=int, help="points a submap (default: the model's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    enc = model_encoder(args.model, None, "float32")
    runs = load_eval_runs(args.root, args.splits, None, None)
    if args.db_layout == "train":
        runs = train_layout_databases(args.root, runs)
    spacing = [
        float(np.median(np.linalg.norm(np.diff(r.db_positions, axis=0), axis=1))) for r in runs
    ]
    print(f"{len(runs)} runs; median database spacing {np.median(spacing):.1f} m")
    _, db, q = embed_runs(enc.embed, runs, args.num_points or enc.num_points, args.workers, True)
    dim = q[0].shape[1]
    if args.joint_map:
        return joint_map(args, runs, db, q, dim)
    base = evaluate_embedded(runs, db, q)
    rows = [{"radius_m": None, "weight": None, **_figures(base)}]
    print(_line("none", rows[0], rows[0]))
    for label, sm in _settings(args, across=(False,))[1:]:
        rep = evaluate_embedded(runs, smooth_databases(runs, db, dim, sm), q)
        rows.append({**sm.to_json(), **_figures(rep)})
        print(_line(label, rows[-1], rows[0]))
    if args.json:
        args.json.write_text(json.dumps({"db_layout": args.db_layout, "rows": rows}, indent=1))
    return 0


def joint_map(args: argparse.Namespace, runs: list, db: list, q: list, dim: int) -> int:
    """``--joint-map``: recall@1 and @10 of each run's queries against one map of the other
    runs of its area, plain, smoothed along each drive and across the drives."""
    areas: dict[str, list[int]] = {}
    for k, r in enumerate(runs):
        areas.setdefault(r.area, []).append(k)
    rows = []
    for label, sm in _settings(args):
        hits = np.zeros(2)
        n = 0
        for j, qrun in enumerate(runs):
            mapped = [i for i in areas[qrun.area] if i != j]
            desc = np.concatenate([db[i] for i in mapped])
            pos = np.concatenate([runs[i].db_positions for i in mapped])
            drives = np.concatenate([np.full(len(db[i]), i) for i in mapped])
            if sm is not None:
                desc = sm.apply(desc, dim, drives, pos)  # across_drives: every drive blends
            nn = exact_search(desc, q[j], 10)
            off = np.linalg.norm(pos[nn] - qrun.query_positions[:, None], axis=2)
            right = (off <= TRUTH_M) & (nn >= 0)  # -1: fewer entries than asked for
            hits += [right[:, 0].sum(), right.any(axis=1).sum()]
            n += len(right)
        rows.append(
            {"setting": label, "recall_at_1": 100 * hits[0] / n, "recall_at_10": 100 * hits[1] / n}
        )
        r1, r10 = rows[-1]["recall_at_1"], rows[-1]["recall_at_10"]
        print(f"{label:<34} recall@1 {r1:6.2f}  recall@10 {r10:6.2f}  ({n} queries)")
    if args.json:
        args.json.write_text(json.dumps({"joint_map": True, "rows": rows}, indent=1))
    return 0


def _settings(args: argparse.Namespace, across: tuple[bool, ...] = (False, True)) -> list:
    """("none", None), then (label, setting) for each radius and weight asked for (by default
    15, 25, 35 m and 0.3, 0.5, 0.7, 1), along each drive and, in ``across``, across them."""
    out: list = [("none", None)]
    for radius in args.radius or [15.0, 25.0, 35.0]:
        for weight in args.weight or [0.3, 0.5, 0.7, 1.0]:
            for across_drives in across:
                what = ", across drives" if across_drives else ""
                out.append(
                    (
                        f"R {radius:g} m, w {weight:g}{what}",
                        Smoothing(radius, weight, across_drives),
                    )
                )
    return out


def _figures(rep: dict) -> dict:
    return {
        "recall_at_1": rep["recall_at_1"],
        "recall_at_1pct": rep["recall_at_1pct"],
        "per_area": {a: v["recall_at_1"] for a, v in rep["per_area"].items()},
    }


def _line(label: str, row: dict, base: dict) -> str:
    areas = (
        "  ".join(f"{a} {v:.2f}" for a, v in row["per_area"].items())
        if len(row["per_area"]) > 1
        else ""
    )
    return (
        f"{label:<18} recall@1 {row['recall_at_1']:6.2f} "
        f"({row['recall_at_1'] - base['recall_at_1']:+.2f})  "
        f"recall@1% {row['recall_at_1pct']:6.2f}  {areas}"
    )


if __name__ == "__main__":
    run(main)
