#!/usr/bin/env bash
# Train three variants of the compact configuration for the same wall-clock budget each,
# evaluate them and the training-free baseline on the same tree, and print one table (per area
# and overall). The paper's orderings come in two sets of three:
#   models: PN_VLAD (lazy quadruplet), PN_MAX (lazy quadruplet), PN_VLAD (quadruplet, sum)
#   losses: PN_VLAD with lazy triplet, with triplet (sum), and lazy quadruplet at 128-d
# Run both sets into one OUT for the whole comparison (the table prints every run it finds).
#
#   bash benchmarks/compare_models.sh [ROOT] [MINUTES] [OUT] [SET]
#   defaults: data/bench (pnvlad synth --preset benchmark --out data/bench), 25, runs/compare,
#   models
#
# The three runs go at once with one torch thread each (benchmarks/configs/compact-short.yaml),
# so they share the machine equally: the same wall-clock budget and the same compute each.
# They train on a fixed random 1024 of each submap's 4096 points (4x the steps in the budget);
# evaluation embeds all 4096, as the index and the server do.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="${1:-data/bench}"
MINUTES="${2:-25}"
OUT="${3:-runs/compare}"
SET="${4:-models}"
POINTS="${PNVLAD_TRAIN_POINTS:-1024}"  # points a cloud while training (all 4096 at evaluation)
CFG=benchmarks/configs/compact-short.yaml
mkdir -p "$OUT"

. benchmarks/compare_lib.sh  # train NAME OPTIONS..., evaluate NAME

case "$SET" in
models) RUNS=(pnvlad_lazyquad pnmax_lazyquad pnvlad_quad)
    train pnvlad_lazyquad --arch pointnetvlad --loss lazy_quadruplet &
    train pnmax_lazyquad --arch pointnet-max --loss lazy_quadruplet &
    train pnvlad_quad --arch pointnetvlad --loss quadruplet & ;;
losses) RUNS=(pnvlad_lazytrip pnvlad_trip pnvlad_lazyquad128)
    train pnvlad_lazytrip --arch pointnetvlad --loss lazy_triplet &
    train pnvlad_trip --arch pointnetvlad --loss triplet &
    train pnvlad_lazyquad128 --arch pointnetvlad --loss lazy_quadruplet \
        --set model.output_dim=128 & ;;
*) echo "SET is models or losses, not '$SET'" >&2; exit 2 ;;
esac
wait
if [ ! -f "$OUT/baseline.json" ]; then
    pnvlad -q eval --baseline --root "$ROOT" --splits "$ROOT/splits.json" \
        -o "$OUT/baseline.json" --no-progress
fi
for m in "${RUNS[@]}"; do evaluate "$m"; done

python - "$OUT" "$MINUTES" <<'EOF'
import json, sys
from pathlib import Path
out, minutes = Path(sys.argv[1]), sys.argv[2]
rows = [
    ("baseline", "Scan-Context-style grid, no training"),
    ("pnvlad_lazyquad", f"PN_VLAD compact, lazy quadruplet, {minutes} min"),
    ("pnmax_lazyquad", f"PN_MAX compact, lazy quadruplet, {minutes} min"),
    ("pnvlad_quad", f"PN_VLAD compact, quadruplet (sum), {minutes} min"),
    ("pnvlad_lazytrip", f"PN_VLAD compact, lazy triplet, {minutes} min"),
    ("pnvlad_trip", f"PN_VLAD compact, triplet (sum), {minutes} min"),
    ("pnvlad_lazyquad128", f"PN_VLAD compact 128-d, lazy quadruplet, {minutes} min"),
]
rows = [(k, label) for k, label in rows if (out / f"{k}.json").exists()]
reports = {k: json.loads((out / f"{k}.json").read_text()) for k, _ in rows}
areas = sorted(reports["baseline"]["per_area"])
head = "| model | " + " | ".join(f"{a} R@1 / R@1%" for a in areas) + " | all R@1 / R@1% |"
print(head)
print("|" + "---|" * (len(areas) + 2))
for k, label in rows:
    r = reports[k]
    cells = [
        f"{r['per_area'][a]['recall_at_1']:.1f} / {r['per_area'][a]['recall_at_1pct']:.1f}"
        for a in areas
    ]
    cells.append(f"{r['recall_at_1']:.1f} / {r['recall_at_1pct']:.1f}")
    print(f"| {label} | " + " | ".join(cells) + " |")
for k, _ in rows[1:]:
    log = [json.loads(l) for l in (out / k / "metrics.jsonl").read_text().splitlines()]
    steps = [e for e in log if e.get("event", "step") == "step" and "loss" in e]
    if steps:
        print(f"{k}: {steps[-1].get('step')} steps, last loss {steps[-1]['loss']:.3f}")
EOF
