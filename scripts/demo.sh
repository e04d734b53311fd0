#!/usr/bin/env bash
# The main job end to end on the built-in synthetic city, from a fresh checkout:
#   1. set up a virtual environment (.venv) with pnvlad and its plot extra;
#   2. generate the `demo` synthetic benchmark (several runs through one city, splits included);
#   3. train the encoder with the best CPU recipe, `-c bev` (bev-netvlad: its 36 epochs take a
#      few minutes on this city; PNVLAD_DEMO_MINUTES caps them, default 5);
#   4. build a FAISS index bundle of every run but one;
#   5. start `pnvlad serve` on 127.0.0.1, localise query submaps of the held-out run over HTTP,
#      print their top-5 with UTM coordinates and distances and whether each is within 25 m;
#      stop the server;
#   6. train the single-scan encoder (-c bev_scan: bev-netvlad on the keyframe maps, each cloud
#      turned to its own dominant direction; 18 epochs, PNVLAD_DEMO_SCAN_MINUTES caps them,
#      default 4) and build a bundle of the indexed runs' keyframes (one scan every 5 m);
#   7. serve it and localise raw single scans of the held-out run, as a robot's sensor makes
#      them, over HTTP.
# Everything goes under runs/demo (PNVLAD_DEMO_DIR). Re-running reuses the city and the model.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV="${PNVLAD_VENV:-.venv}"
OUT="${PNVLAD_DEMO_DIR:-runs/demo}"
MINUTES="${PNVLAD_DEMO_MINUTES:-5}"
SCAN_MINUTES="${PNVLAD_DEMO_SCAN_MINUTES:-4}"
PORT="${PNVLAD_DEMO_PORT:-8765}"
SEED="${PNVLAD_DEMO_SEED:-0}"
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

MODEL="$OUT/train"
step "3/7 train the bev-netvlad encoder (-c bev, at most $MINUTES min) -> $MODEL"
if [ ! -f "$MODEL/model/model.json" ]; then
    pnvlad train -c bev --root "$CITY" --splits "$CITY/splits.json" -o "$MODEL" \
        --max-minutes "$MINUTES"
fi

BUNDLE="$OUT/map.index"
step "4/7 index bundle of $DATASET without $HELD -> $BUNDLE"
run_args=()
IFS=',' read -ra runs <<< "$INDEXED"
for r in "${runs[@]}"; do run_args+=(--run "$r"); done
pnvlad index build -m "$MODEL/model" -r "$CITY" -d "$DATASET" "${run_args[@]}" -o "$BUNDLE" --overwrite

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
serve "$BUNDLE" "$MODEL/model"
python scripts/demo_localize.py --url "http://127.0.0.1:$PORT" --root "$CITY" \
    --dataset "$DATASET" --run "$HELD" --count 6 --top-n 5
stop

SCAN_MODEL="$OUT/train_scan"
KEYS="$OUT/keyframes.index"
step "6/7 train the single-scan encoder (-c bev_scan, at most $SCAN_MINUTES min), index keyframes"
if [ ! -f "$SCAN_MODEL/model/model.json" ]; then
    pnvlad train -c bev_scan --root "$CITY" --splits "$CITY/splits_keyframes.json" \
        -o "$SCAN_MODEL" --epochs 18 --max-minutes "$SCAN_MINUTES"
fi
pnvlad index build -m "$SCAN_MODEL/model" -r "$CITY" -d "$DATASET" "${run_args[@]}" \
    --layout keyframe -o "$KEYS" --overwrite

step "7/7 serve the keyframe map and localise held-out raw single scans"
serve "$KEYS" "$SCAN_MODEL/model"
python scripts/demo_localize.py --url "http://127.0.0.1:$PORT" --root "$CITY" \
    --dataset "$DATASET" --run "$HELD" --count 6 --top-n 5 --scans
stop

step "done"
