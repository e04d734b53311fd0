"""Learning curves of several `pnvlad train` runs on one figure (docs/results/training.md's
recipe table): smoothed loss and validation recall@1 / recall@1% against wall-clock minutes.

    python benchmarks/plot_runs.py runs/a runs/b --names base augmented -o curves.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from entry import run

from pnvlad_service.training.curves import read_curve, write_learning_curves


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="Run folders (or their metrics.jsonl).")
    ap.add_argument("--names", nargs="+", help="A label a run (default: the folder names).")
    ap.add_argument("-o", "--out", type=Path, required=True, help="PNG to write.")
    ap.add_argument("--title", help="Figure title.")
    args = ap.parse_args()
    names = args.names or [None] * len(args.runs)
    if len(names) != len(args.runs):
        ap.error("give one --names label a run")
    curves = [read_curve(r, n) for r, n in zip(args.runs, names, strict=True)]
    print(write_learning_curves(curves, args.out, args.title))


if __name__ == "__main__":
    run(main)
