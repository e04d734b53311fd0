#!/usr/bin/env bash
# Tuple training (the paper: cached hard negatives) against in-batch mining, PN_VLAD compact with
# lazy quadruplet, the same wall-clock budget and one torch thread each (the two runs go at
# once, one per core), evaluated on the same tree. Prints one table (per area and overall).
#
#   bash benchmarks/compare_mining.sh [ROOT] [MINUTES] [OUT]
#   defaults: data/bench (pnvlad synth --preset benchmark --out data/bench), 60, runs/compare60
#
# Both train on a fixed random 1024 of each submap's 4096 points; evaluation embeds all 4096.
# In-batch steps take 16 anchors and a positive each (32 clouds; tuple steps take 4 tuples of
# 22 clouds); everything else is benchmarks/configs/compact-short.yaml.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="${1:-data/bench}"
MINUTES="${2:-60}"
OUT="${3:-runs/compare60}"
POINTS="${PNVLAD_TRAIN_POINTS:-1024}"
CFG=benchmarks/configs/compact-short.yaml
mkdir -p "$OUT"

. benchmarks/compare_lib.sh  # train NAME OPTIONS..., evaluate NAME

LAZYQUAD=(--arch pointnetvlad --loss lazy_quadruplet)
train tuple_lazyquad "${LAZYQUAD[@]}" --mining tuple &
train inbatch_lazyquad "${LAZYQUAD[@]}" --mining in_batch -b 16 &
wait
for m in tuple_lazyquad inbatch_lazyquad; do evaluate "$m"; done

python - "$OUT" "$MINUTES" <<'PY'
import json, sys
from pathlib import Path
out, minutes = Path(sys.argv[1]), sys.argv[2]
rows = [("tuple_lazyquad", "tuples + cached hard negatives"), ("inbatch_lazyquad", "in-batch")]
reports = {k: json.loads((out / f"{k}.json").read_text()) for k, _ in rows}
areas = sorted(reports[rows[0][0]]["per_area"])
print("| mining | steps | " + " | ".join(f"{a} R@1 / R@1%" for a in areas) + " | all R@1 / R@1% |")
print("|" + "---|" * (len(areas) + 3))
for k, label in rows:
    r = reports[k]
    log = [json.loads(line) for line in (out / k / "metrics.jsonl").read_text().splitlines()]
    steps = max((e.get("step", 0) for e in log), default=0)
    cells = [
        f"{r['per_area'][a]['recall_at_1']:.1f} / {r['per_area'][a]['recall_at_1pct']:.1f}"
        for a in areas
    ]
    cells.append(f"{r['recall_at_1']:.1f} / {r['recall_at_1pct']:.1f}")
    print(f"| {label}, {minutes} min | {steps} | " + " | ".join(cells) + " |")
PY
