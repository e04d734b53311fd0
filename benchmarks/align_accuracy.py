"""A map's accuracy against the simulator's truth before and after `pnvlad map align`.

    pnvlad map align bench/ -o bench-aligned/
    python benchmarks/align_accuracy.py --recorded bench/ --aligned bench-aligned/

Prints, for the keyframes and the 20 m test submaps of both trees, the position error of the
entries against the simulator's truth (median, p90, p99, max), their yaw error, and the
disagreement between runs at one place (each entry against the truly nearest entry of every
other run within 2.5 m: how far apart the two runs put the same point), for the whole tree and,
where it holds several datasets (districts), for each; then the alignment's
closures, residuals and the time of each stage from the aligned tree's align_report.json.
Both trees are read from their frame sidecars (pnvlad_service/mapping/accuracy.py), so the
figures do not depend on how the alignment computed them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from entry import run


def _row(name: str, s: dict) -> str:
    p, y, d = s["position_error_m"], s["yaw_error_deg"], s["disagreement_m"]
    return (
        f"{name:<22} {s['entries']:>6} {p['median']:>7.3f} {p['p90']:>7.3f} {p['p99']:>7.3f} "
        f"{p['max']:>7.3f} {y['median']:>8.3f} {s['pairs']:>7} {d['median']:>8.3f} "
        f"{d['p90']:>7.3f} {d['p99']:>7.3f}"
    )


def main() -> int:
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.mapping.accuracy import tree_accuracy

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recorded", type=Path, required=True, help="the tree as recorded")
    ap.add_argument("--aligned", type=Path, required=True, help="its pnvlad map align output")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    head = (
        f"{'tree, kind':<22} {'entries':>6} {'median':>7} {'p90':>7} {'p99':>7} {'max':>7} "
        f"{'yaw med':>8} {'pairs':>7} {'disagree':>8} {'p90':>7} {'p99':>7}"
    )
    print("position error against the truth (m), yaw error (deg), disagreement between runs (m)")
    print(head)
    out: dict = {}
    datasets = BenchmarkTree(args.recorded).datasets
    parts = [None] + (datasets if len(datasets) > 1 else [])
    for part in parts:
        if part is not None:
            print(f"dataset {part}:")
        for kind in ("keyframe", "test"):
            for name, root in (("recorded", args.recorded), ("aligned", args.aligned)):
                s = tree_accuracy(root, kind, dataset=part).summary()  # type: ignore[arg-type]
                key = f"{name}/{kind}" if part is None else f"{part}/{name}/{kind}"
                out[key] = s
                print(_row(f"{name}, {kind}", s))
    report = json.loads((args.aligned / "align_report.json").read_text())
    c = report["closures"]
    print(
        f"nodes {report['nodes']}, odometry {report['odometry']['accepted']}/"
        f"{report['odometry']['steps']}, closures {c['accepted']} accepted / {c['rejected']} "
        f"rejected of {report['candidates']}"
    )
    print("residuals (m):", json.dumps(report["residuals_m"]))
    print("graph:", json.dumps(report["graph"]))
    print("stages (s):", json.dumps(report["seconds"]))
    out["report"] = {k: report[k] for k in ("nodes", "candidates", "residuals_m", "seconds")}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    run(main)
