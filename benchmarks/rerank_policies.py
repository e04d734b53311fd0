"""The re-ranking cascade's policies side by side on one embedding (issue #10: what closes the
gap between recall@1 after re-ranking and recall@K before).

    python benchmarks/rerank_policies.py MODEL TREE --threshold 0.11 \
        [--policy shipped --policy all --policy stop0.35 --policy k6 ...]

Embeds TREE's evaluation runs once with MODEL (as ``pnvlad eval --num-points 4096``), then runs
``evaluation.rerank.rerank_report`` for each policy with the same threshold (give the one
``pnvlad eval --rerank 10`` chose on the training layout), and prints per policy: recall@1
before and after, recall@K before and the gap, recall@1% after, the metric success and median
errors, ``verified`` precision by place and pose with its coverage, candidates registered a
query and the seconds it took, overall and per area.

Policies: ``shipped`` (VerifyConfig's defaults), ``all`` (every candidate registered: no early
stop), ``stopX`` (stop score X), ``minN`` (at least N registered), ``kN`` (N candidates),
``radiusX`` (a candidate that places the query farther than X m from its origin ranks after
the rest; 25 shipped), ``aloneX`` (a first candidate that scores X and pins the translation
ends the cascade alone; 0.35 shipped, ``alone1`` never).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import run

from pnvlad_service.data.dataset import load_eval_runs
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.evaluation.evaluate import embed_runs, model_encoder
from pnvlad_service.evaluation.rerank import _reversed_runs, rerank_report
from pnvlad_service.localization.verify.verify import VerifyConfig


def policy(name: str, threshold: float) -> VerifyConfig:
    base = VerifyConfig(threshold=threshold)
    if name == "shipped":
        return base
    if name == "all":
        return replace(base, stop_score=None)
    if name.startswith("stop"):
        return replace(base, stop_score=float(name[4:]))
    if name.startswith("alone"):
        x = float(name[5:])
        return replace(base, alone_score=x if x < 1.0 else None)
    if name.startswith("radius"):
        return replace(base, place_radius_m=float(name[6:]))
    if name.startswith("min"):
        return replace(base, min_registered=int(name[3:]))
    if name.startswith("k"):
        return replace(base, candidates=int(name[1:]))
    raise SystemExit(f"unknown policy {name!r} (shipped, all, stopX, minN, kN, radiusX, aloneX)")


def line(label: str, r: dict) -> str:
    m, v = r["metric"], r["verified"]
    gap = r["recall_at_k_before"] - r["recall_at_1_after"]
    return (
        f"  {label:12s} recall@1 {r['recall_at_1_before']:.1f} -> {r['recall_at_1_after']:.1f} %"
        f" (recall@{r['candidates']} {r['recall_at_k_before']:.1f}: {gap:.1f} under),"
        f" recall@1% after {r['recall_at_1pct_after']:.1f}; success {m['success']:.1f} % of"
        f" {m['n']}, {m['median_translation_m']:.3f} m / {m['median_yaw_deg']:.3f} deg;"
        f" verified {v['precision']:.1f} / {v['pose_precision']:.1f} % at"
        f" {v['coverage']:.1f} %; {r['registered_mean']:.2f} registered"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("tree", type=Path)
    ap.add_argument("--splits", type=Path, help="default: TREE/splits.json")
    ap.add_argument("--threshold", type=float, required=True)
    ap.add_argument("--policy", action="append", help="(repeatable; default: shipped, all)")
    args = ap.parse_args()
    splits = args.splits or args.tree / "splits.json"
    enc = model_encoder(args.model)
    runs = load_eval_runs(args.tree, splits, None, None)
    _, db, q = embed_runs(enc.embed, runs, 4096, 4, False)
    frames = BenchmarkTree(args.tree).frames_by_path()
    reversed_runs = _reversed_runs(args.tree)
    for name in args.policy or ["shipped", "all"]:
        rep, _ = rerank_report(
            runs, db, q, frames, policy(name, args.threshold), reversed_runs=reversed_runs
        )
        print(f"== {name}: {rep['seconds']:.0f} s", flush=True)
        print(line("all areas", rep))
        for area, r in rep["per_area"].items():
            print(line(area, r))


if __name__ == "__main__":
    run(main)
