"""How alike a tree's places look: simple descriptors of its submaps after G, run against run.

For every run's test submaps (``pointcloud_20m``, 20 m apart) three training-free descriptors
that each see one thing a place is told apart by:

- ``height``: the histogram of the points' heights (16 bins over [-1, 1]): the street's
  height profile (how tall its buildings and trees are, where the mass sits);
- ``footprint``: the share of points in each cell of a 12 x 12 grid over [-1, 1]²: the plan
  (setbacks, gaps, side streets, trees' positions);
- ``height map``: the highest point of each of those cells (-1.2 where empty): plan and
  height together (roof lines, crowns over the pavement).

Per descriptor, every run's submaps against every other run's (L2, nearest neighbour):
recall@1 (the nearest within 25 m), the share of queries that a place 50 m or more away
matches better than their own place, and the *neighbour contrast*: the median distance
between consecutive submaps of one run (20 m apart) over the median distance between a place
and itself in another run (the nearest within 5 m). A contrast near 1 says that moving 20 m
changes a submap about as little as driving the same place again: places look alike.

    python benchmarks/place_similarity.py /work/data/ox_base /work/data/ox_var
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from pnvlad_service.io.submap import read_submap

GRID, BINS = 12, 16


def _runs(tree: Path) -> list[tuple[np.ndarray, list[Path]]]:
    """(northing/easting [N, 2], submap paths) of each run's test submaps."""
    out = []
    for csv_path in sorted(tree.glob("*/*/pointcloud_locations_20m.csv")):
        with csv_path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        xy = np.array([[float(r["northing"]), float(r["easting"])] for r in rows])
        paths = [csv_path.parent / "pointcloud_20m" / f"{r['timestamp']}.bin" for r in rows]
        out.append((xy, paths))
    return out


def descriptors(points: np.ndarray) -> dict[str, np.ndarray]:
    """The three descriptors of one submap after G (points [N, 3] in [-1, 1])."""
    p = np.clip(points, -1.0, 1.0 - 1e-9)
    height = np.histogram(p[:, 2], BINS, (-1.0, 1.0))[0] / len(p)
    cell = ((p[:, 0] + 1) / 2 * GRID).astype(int) * GRID + ((p[:, 1] + 1) / 2 * GRID).astype(int)
    foot = np.bincount(cell, minlength=GRID * GRID) / len(p)
    top = np.full(GRID * GRID, -1.2)
    np.maximum.at(top, cell, p[:, 2])
    return {"height": height * 4, "footprint": foot * GRID, "height map": top}


def measure(tree: Path) -> dict[str, dict[str, float]]:
    runs = _runs(tree)
    if len(runs) < 2:
        sys.exit(f"{tree}: fewer than two runs with pointcloud_locations_20m.csv")
    desc = [[descriptors(read_submap(p)) for p in paths] for _, paths in runs]
    out: dict[str, dict[str, float]] = {}
    for name in ("height", "footprint", "height map"):
        d = [np.stack([x[name] for x in run]) for run in desc]
        hits, fooled, n, same, step = 0, 0, 0, [], []
        for a, (xa, _) in enumerate(runs):
            step += list(np.linalg.norm(np.diff(d[a], axis=0), axis=1))
            for b, (xb, _) in enumerate(runs):
                if a == b:
                    continue
                geo = np.linalg.norm(xa[:, None] - xb[None], axis=2)
                dd = np.linalg.norm(d[a][:, None] - d[b][None], axis=2)
                for q in range(len(xa)):
                    if geo[q].min() > 25.0:
                        continue
                    n += 1
                    hits += geo[q, int(np.argmin(dd[q]))] <= 25.0
                    far = geo[q] >= 50.0
                    fooled += far.any() and dd[q][far].min() < dd[q][geo[q] <= 25.0].min()
                    if geo[q].min() <= 5.0:
                        same.append(dd[q, int(np.argmin(geo[q]))])
        out[name] = {
            "recall@1 %": round(100.0 * hits / max(n, 1), 1),
            "a far place nearer %": round(100.0 * fooled / max(n, 1), 1),
            "neighbour contrast": round(float(np.median(step) / max(np.median(same), 1e-9)), 2),
            "queries": n,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trees", nargs="+", type=Path, help="pnvlad synth trees (or any Oxford tree)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    res = {str(t): measure(t) for t in args.trees}
    for tree, figs in res.items():
        print(f"## {tree}")
        print("| descriptor | recall@1 | a far place nearer | neighbour contrast | queries |")
        print("|---|---|---|---|---|")
        for name, f in figs.items():
            print(
                f"| {name} | {f['recall@1 %']} % | {f['a far place nearer %']} % "
                f"| {f['neighbour contrast']} | {f['queries']} |"
            )
    if args.json:
        args.json.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
