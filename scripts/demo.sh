#!/usr/bin/env bash
# The main job end to end on the built-in synthetic city, from a fresh checkout:
#   1. set up a virtual environment (.venv) with pnvlad and its plot extra;
#   2. generate the `demo` synthetic benchmark (several runs through one city, splits included);
#   3. the submap encoder: the shipped pretrained:bev-mixed (bev-netvlad trained on the
#      `benchmark` preset's spinning and the `oxford` preset's push-broom submaps; no training
#      run). PNVLAD_DEMO_TRAIN=1 trains `-c bev` on this city
#      instead (its 36 epochs take a few minutes; PNVLAD_DEMO_MINUTES caps them, default 5);
#   4. build a FAISS index bundle of every run but one;
#   5. start `pnvlad serve` on 127.0.0.1, localise query submaps of the held-out run over HTTP,
#      print their top-5 with UTM coordinates and distances and whether each is within 25 m;
#      stop the server;
#   6. the single-scan encoder: the shipped pretrained:bev-scan-benchmark (with
#      PNVLAD_DEMO_TRAIN=1: `-c bev_scan` trained here, 18 epochs, PNVLAD_DEMO_SCAN_MINUTES caps
#      them, default 4), and a bundle of the indexed runs' keyframes (one scan every 5 m);
#   7. serve it and localise raw single scans of the held-out run, as a robot's sensor makes
#      them, over HTTP.
# Everything goes under runs/demo (PNVLAD_DEMO_DIR). Re-running reuses the city and trained models.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV="${PNVLAD_VENV:-.venv}"
OUT="${PNVLAD_DEMO_DIR:-runs/demo}"
MINUTES="${PNVLAD_DEMO_MINUTES:-5}"
SCAN_MINUTES="${PNVLAD_DEMO_SCAN_MINUTES:-4}"
PORT="${PNVLAD_DEMO_PORT:-8765}"
SEED="${PNVLAD_DEMO_SEED:-0}"
TRAIN="${PNVLAD_DEMO_TRAIN:-0}"
start=$(date +%s)

step() { printf '\n\033[1m== %s\033[0m  (%ds)\n' "$*" "$(( $(date +%s) - start ))"; }

step "1/7 set up $VENV"
. scripts/venv.sh
ensure_venv torch,plot
export PATH="$PWD/$VENV/bin:$PATH"
pnvlad --version

CITY="$OUT/city"
step "2/7 synthetic city -> $CITY"
if [ ! -f "$CITY/splits_keyframes.json" ]; then
    pnvlad -q synth --preset demo --seed "$SEED" --out "$CITY" --overwrite
fi
pnvlad data check "$CITY"

# The first dataset (area) of the tree, its last run held out of the index as the query run.
read -r DATASET HELD INDEXED < <(python - "$CITY" <<'EOF'
import sys
from pnvlad_service.data.tree import BenchmarkTree
tree = BenchmarkTree(sys.argv[1])
ds = tree.datasets[0]
runs = tree.runs(ds)
print(ds, runs[-1], ",".join(runs[:-1]))
EOF
)
echo "area $DATASET: index runs ${INDEXED//,/ }; queries from held-out run $HELD"

if [ "$TRAIN" = 1 ]; then
    MODEL="$OUT/train/model"
    step "3/7 train the bev-netvlad encoder (-c bev, at most $MINUTES min) -> $MODEL"
    if [ ! -f "$MODEL/model.json" ]; then
        pnvlad train -c bev --root "$CITY" --splits "$CITY/splits.json" -o "$OUT/train" \
            --max-minutes "$MINUTES"
    fi
else
    MODEL="pretrained:bev-mixed"
    step "3/7 the submap encoder: $MODEL (shipped; PNVLAD_DEMO_TRAIN=1 trains one here)"
    pnvlad model info "$MODEL" | grep -E "^  (trained_with|figures) "
fi

BUNDLE="$OUT/map.index"
step "4/7 index bundle of $DATASET without $HELD -> $BUNDLE"
run_args=()
IFS=',' read -ra runs <<< "$INDEXED"
for r in "${runs[@]}"; do run_args+=(--run "$r"); done
pnvlad index build -m "$MODEL" -r "$CITY" -d "$DATASET" "${run_args[@]}" -o "$BUNDLE" --overwrite

# serve BUNDLE MODEL: start `pnvlad serve` in the background and wait until it is ready.
serve() {
    pnvlad serve --index "$1" --checkpoint "$2" --host 127.0.0.1 --port "$PORT" \
        --log-level warning &
    server=$!
    trap 'kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true' EXIT
    for _ in $(seq 1 120); do
        if python - "$PORT" <<'EOF' 2>/dev/null
import sys, urllib.request
urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[1]}/readyz", timeout=1)
EOF
        then return 0; fi
        if ! kill -0 "$server" 2>/dev/null; then echo "the server exited" >&2; exit 1; fi
        sleep 0.5
    done
}
stop() { kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; }

step "5/7 serve on 127.0.0.1:$PORT and localise held-out query submaps"
serve "$BUNDLE" "$MODEL"
python scripts/demo_localize.py --url "http://127.0.0.1:$PORT" --root "$CITY" \
    --dataset "$DATASET" --run "$HELD" --count 6 --top-n 5
stop

KEYS="$OUT/keyframes.index"
if [ "$TRAIN" = 1 ]; then
    SCAN_MODEL="$OUT/train_scan/model"
    step "6/7 train the single-scan encoder (-c bev_scan, at most $SCAN_MINUTES min), index keyframes"
    if [ ! -f "$SCAN_MODEL/model.json" ]; then
        pnvlad train -c bev_scan --root "$CITY" --splits "$CITY/splits_keyframes.json" \
            -o "$OUT/train_scan" --epochs 18 --max-minutes "$SCAN_MINUTES"
    fi
else
    SCAN_MODEL="pretrained:bev-scan-benchmark"
    step "6/7 the single-scan encoder: $SCAN_MODEL (shipped), index keyframes"
fi
pnvlad index build -m "$SCAN_MODEL" -r "$CITY" -d "$DATASET" "${run_args[@]}" \
    --layout keyframe -o "$KEYS" --overwrite

step "7/7 serve the keyframe map and localise held-out raw single scans"
serve "$KEYS" "$SCAN_MODEL"
python scripts/demo_localize.py --url "http://127.0.0.1:$PORT" --root "$CITY" \
    --dataset "$DATASET" --run "$HELD" --count 6 --top-n 5 --scans
stop

step "done"
