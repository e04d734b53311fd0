"""How often registration poses a *true* candidate right, by its distance from the query
(issue #10: what bounds recall@1 after re-ranking). Model-free: the candidates are each test
query's true database submaps (within 25 m by the tree's ground truth), so no encoder decides
which are registered.

    python benchmarks/registration_by_distance.py TREE [--per-pair 4] [--variant default ...]

TREE: a ``pnvlad synth`` tree (its frame sidecars carry the true poses). For a sample of
queries of every ordered run pair of each area, each true candidate and two false ones
(>= 60 m away) are registered with each registration variant; a true one is right when the
estimated query -> candidate transform is within 2 m and 5 degrees of the true relative pose.
Prints, per variant, the share right by true distance and by area, the fitness of the false
pairs, and milliseconds a pair (preparation included).

Variants: ``default`` (the shipped RegistrationConfig), ``hyp2`` (the coarse stage started from
the two best yaw/shift hypotheses), ``local`` (the target is the candidate merged with its
run's database neighbours within 20 m, placed by their map poses: more overlap for a far
query).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import run

from pnvlad_service.data.dataset import load_eval_runs
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.evaluation.rerank import _Store
from pnvlad_service.evaluation.rerank_figures import pose_error
from pnvlad_service.localization.verify import registration as reg

VARIANTS = {
    "default": {},
    # the default until session 12: 64 cells of 1 m, so the search saw only +-32 m
    "narrow64": {"bev_cells": 64, "search_radius_m": 40.0},
    "hyp2": {"hypotheses": 2},
    "local": {},
    "wide": {"bev_cells": 96, "search_radius_m": 48.0},
    "wide-hyp2": {"bev_cells": 96, "search_radius_m": 48.0, "hypotheses": 2},
    "peaks3-hyp3": {"yaw_peaks": 3, "hypotheses": 3},
    "white1": {"whitening": 1.0},
    "wide128": {"bev_cells": 128, "search_radius_m": 64.0},
    "wide160": {"bev_cells": 160, "search_radius_m": 80.0},
    "cell2": {"bev_cells": 64, "bev_cell_m": 2.0, "search_radius_m": 64.0},
    "cell1.5": {"bev_cells": 96, "bev_cell_m": 1.5, "search_radius_m": 72.0},
    "wide128-hyp2": {"bev_cells": 128, "search_radius_m": 64.0, "hypotheses": 2},
}
LOCAL_M = 20.0
BINS = [(0, 5), (5, 10), (10, 15), (15, 20), (20, 25), (25, 40)]


def sample_pairs(runs, per_pair: int, rng) -> list[tuple[str, int, int, int, int, bool]]:
    """(area, db run, query run, query, db row, is true) to register."""
    areas: dict[str, list[int]] = {}
    for k, r in enumerate(runs):
        areas.setdefault(r.area, []).append(k)
    jobs = []
    for area, members in areas.items():
        for i in members:
            for j in [m for m in members if m != i]:
                qs = [q for q, t in enumerate(runs[j].truth) if len(t.get(i, [])) > 0]
                for q in rng.choice(qs, size=min(per_pair, len(qs)), replace=False):
                    jobs += [(area, i, j, int(q), int(r), True) for r in runs[j].truth[q][i]]
                    d = np.linalg.norm(runs[i].db_positions - runs[j].query_positions[q], axis=1)
                    far = np.flatnonzero(d > 60)
                    for r in rng.choice(far, size=min(2, len(far)), replace=False):
                        jobs.append((area, i, j, int(q), int(r), False))
    return jobs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tree", type=Path)
    ap.add_argument("--per-pair", type=int, default=4, help="queries a run pair")
    ap.add_argument("--variant", action="append", choices=sorted(VARIANTS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    runs = load_eval_runs(args.tree, args.tree / "splits.json")
    # Metres as a bundle stores them, read once per submap (the re-ranking evaluation's store).
    get = _Store(BenchmarkTree(args.tree).frames_by_path()).get

    def local_points(i: int, row: int) -> np.ndarray:
        pts, f = get(runs[i].db_paths[row])
        d = np.linalg.norm(runs[i].db_positions - runs[i].db_positions[row], axis=1)
        parts = [pts]
        for n in np.flatnonzero((d <= LOCAL_M) & (d > 0)):
            near, nf = get(runs[i].db_paths[n])
            parts.append(near + (nf.origin - f.origin))
        return np.concatenate(parts)

    jobs = sample_pairs(runs, args.per_pair, np.random.default_rng(args.seed))
    print(f"{len(jobs)} pairs a variant ({sum(j[5] for j in jobs)} true)")
    for _, i, j, q, row, _ in jobs:  # read before any variant is timed
        get(runs[j].query_paths[q]), get(runs[i].db_paths[row])
    reg.register(*(get(runs[j].query_paths[q])[0] for _ in range(2)))  # small_gicp loaded
    for name in args.variant or ["default", "hyp2", "local"]:
        cfg = replace(reg.DEFAULT, **VARIANTS[name])
        sources, targets, rows = {}, {}, []
        t0 = time.perf_counter()
        for area, i, j, q, row, is_true in jobs:
            q_pts, qf = get(runs[j].query_paths[q])
            if (j, q) not in sources:
                sources[(j, q)] = reg.prepare(q_pts, cfg, "source")
            if (i, row) not in targets:
                pts = local_points(i, row) if name == "local" else get(runs[i].db_paths[row])[0]
                targets[(i, row)] = reg.prepare(pts, cfg, "target")
            r = reg.register(sources[(j, q)], targets[(i, row)], cfg)
            rel = np.linalg.inv(get(runs[i].db_paths[row])[1].true_pose) @ qf.true_pose
            te, ye = pose_error(r.transform, rel)
            rows.append((area, is_true, float(np.hypot(*rel[:2, 3])), te < 2 and ye < 5, r.fitness))
        ms = 1000 * (time.perf_counter() - t0) / len(rows)
        true = [r for r in rows if r[1]]
        print(f"== {name}: {ms:.0f} ms a pair, preparation included")
        for lo, hi in BINS:
            b = [r for r in true if lo <= r[2] < hi]
            if b:
                right = 100 * np.mean([r[3] for r in b])
                print(f"  true {lo:2d}-{hi:2d} m: {len(b):4d}, {right:5.1f} % right")
        for area in sorted({r[0] for r in true}):
            b = [r for r in true if r[0] == area]
            print(f"  {area}: {100 * np.mean([r[3] for r in b]):.1f} % right of {len(b)}")
        fit = np.array([r[4] for r in rows if not r[1]])
        if len(fit):
            print(
                f"  false: {len(fit)}, fitness median {np.median(fit):.3f}, "
                f"p99 {np.percentile(fit, 99):.3f}, max {fit.max():.3f}"
            )


if __name__ == "__main__":
    run(main)
