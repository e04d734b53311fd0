"""How much G's scale changes between two drives of one place: what scale augmentation must cover.

Filter G draws every submap at its own scale (mean distance from the centroid 0.5), so one
place recorded on two drives is drawn at two sizes whenever what the drives saw differs (a far
facade down a side street on one drive and not the other, a parked truck, another sensor's
range). The network sees the same street larger or smaller; the training's scale augmentation
(``train.augment.scale``: 1 +- s) is what teaches it that this is the same place.

Per area of a tree (the test-layout submaps, ``pointcloud_20m``, with their ``.frames.csv``
sidecars as ``pnvlad synth`` and ``pnvlad data prepare`` write them): G's scale (metres a
normalised unit) over its submaps, and, for every submap and every other run's submap of the
same place (the nearest by true position, within 5 m; the recorded position where a sidecar
has no truth), the ratio of the larger scale to the smaller: its median, 75th and 90th
percentile, and the share of pairs beyond 1.03 and 1.25 (what ``train.augment.scale`` 0.03 and
0.25 reach).

    python benchmarks/scale_between_runs.py TREE [TREE ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from entry import run

from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import InputError

SAME_PLACE_M = 5.0


def _runs(tree: BenchmarkTree, area: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(positions [N, 2], G's scales [N]) of each run of an area whose test submaps have a
    frames sidecar."""
    out = []
    for name in tree.runs(area):
        frames = tree.frames(area, name, "test") if tree.has(area, name, "test") else None
        if not frames:
            continue
        xy = np.array(
            [(f.true_position if f.true_position is not None else f.origin)[:2] for f in frames]
        )
        out.append((xy, np.array([f.scale for f in frames])))
    return out


def measure(tree: BenchmarkTree, area: str) -> dict[str, float] | None:
    """The area's figures, or None when it has fewer than two runs with sidecars."""
    runs = _runs(tree, area)
    if len(runs) < 2:
        return None
    ratios = []
    for a, (xa, sa) in enumerate(runs):
        for b, (xb, sb) in enumerate(runs):
            if a == b:
                continue
            geo = np.linalg.norm(xa[:, None] - xb[None], axis=2)
            near, same = geo.argmin(1), geo.min(1) <= SAME_PLACE_M
            r = sa[same] / sb[near[same]]
            ratios.append(np.maximum(r, 1.0 / r))
    r = np.concatenate(ratios)
    scales = np.concatenate([s for _, s in runs])
    p10, p50, p90 = np.percentile(scales, [10, 50, 90])
    q50, q75, q90 = np.percentile(r, [50, 75, 90])
    return {
        "submaps": len(scales),
        "scale m p10": round(float(p10), 1),
        "scale m p50": round(float(p50), 1),
        "scale m p90": round(float(p90), 1),
        "pairs": len(r),
        "ratio p50": round(float(q50), 3),
        "ratio p75": round(float(q75), 3),
        "ratio p90": round(float(q90), 3),
        "beyond 1.03 %": round(100.0 * float(np.mean(r > 1.03)), 1),
        "beyond 1.25 %": round(100.0 * float(np.mean(r > 1.25)), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trees", nargs="+", type=Path, help="trees of areas (a pnvlad synth --out)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    res: dict[str, dict[str, float]] = {}
    for root in args.trees:
        tree = BenchmarkTree(root)
        for area in tree.datasets:
            figs = measure(tree, area)
            if figs is not None:
                res[f"{root.name}/{area}"] = figs
    if not res:
        raise InputError("no area with two runs of frames sidecars", source=str(args.trees[0]))
    print(
        "| area | submaps | G's scale, m a unit: p10 / p50 / p90 | same place on two drives: "
        "scale ratio p50 / p75 / p90 | pairs beyond 1.03 / 1.25 |"
    )
    print("|---|---|---|---|---|")
    for name, f in res.items():
        print(
            f"| {name} | {f['submaps']} | {f['scale m p10']} / {f['scale m p50']} / "
            f"{f['scale m p90']} | {f['ratio p50']} / {f['ratio p75']} / {f['ratio p90']} "
            f"({f['pairs']} pairs) | {f['beyond 1.03 %']} / {f['beyond 1.25 %']} % |"
        )
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    run(main)
