#!/usr/bin/env bash
# The main job end to end on the built-in synthetic city, from a fresh checkout:
#   1. set up a virtual environment (.venv) with pnvlad and its plot extra;
#   2. generate the `demo` synthetic benchmark (several runs through one city, splits included);
#   3. train the encoder with the best CPU recipe, `-c bev` (bev-netvlad: its 36 epochs take a
#      few minutes on this city; PNVLAD_DEMO_MINUTES caps them, default 5);
#   4. build a FAISS index bundle of every run but one;
#   5. start `pnvlad serve` on 127.0.0.1, localise query submaps of the held-out run over HTTP,
#      print their top-5 with UTM coordinates and distances and whether each is within 25 m;
#   6. stop the server.
# Everything goes under runs/demo (PNVLAD_DEMO_DIR). Re-running reuses the city and the model.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV="${PNVLAD_VENV:-.venv}"
OUT="${PNVLAD_DEMO_DIR:-runs/demo}"
MINUTES="${PNVLAD_DEMO_MINUTES:-5}"
PORT="${PNVLAD_DEMO_PORT:-8765}"
SEED="${PNVLAD_DEMO_SEED:-0}"
start=$(date +%s)

step() { printf '\n\033[1m== %s\033[0m  (%ds)\n' "$*" "$(( $(date +%s) - start ))"; }

step "1/5 set up $VENV"
. scripts/venv.sh
ensure_venv plot
export PATH="$PWD/$VENV/bin:$PATH"
pnvlad --version

CITY="$OUT/city"
step "2/5 synthetic city -> $CITY"
if [ ! -f "$CITY/splits.json" ]; then
    pnvlad -q synth --preset demo --seed "$SEED" --out "$CITY"
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
step "3/5 train the bev-netvlad encoder (-c bev, at most $MINUTES min) -> $MODEL"
if [ ! -f "$MODEL/model/model.json" ]; then
    pnvlad train -c bev --root "$CITY" --splits "$CITY/splits.json" -o "$MODEL" \
        --max-minutes "$MINUTES"
fi

BUNDLE="$OUT/map.index"
step "4/5 index bundle of $DATASET without $HELD -> $BUNDLE"
run_args=()
IFS=',' read -ra runs <<< "$INDEXED"
for r in "${runs[@]}"; do run_args+=(--run "$r"); done
pnvlad index build -m "$MODEL/model" -r "$CITY" -d "$DATASET" "${run_args[@]}" -o "$BUNDLE" --overwrite

step "5/5 serve on 127.0.0.1:$PORT and localise held-out queries"
pnvlad serve --index "$BUNDLE" --checkpoint "$MODEL/model" --host 127.0.0.1 --port "$PORT" \
    --log-level warning &
server=$!
trap 'kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true' EXIT
for _ in $(seq 1 120); do
    if python - "$PORT" <<'EOF' 2>/dev/null
import sys, urllib.request
urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[1]}/readyz", timeout=1)
EOF
    then break; fi
    if ! kill -0 "$server" 2>/dev/null; then echo "the server exited" >&2; exit 1; fi
    sleep 0.5
done
python scripts/demo_localize.py --url "http://127.0.0.1:$PORT" --root "$CITY" \
    --dataset "$DATASET" --run "$HELD" --count 6 --top-n 5

step "done: stopping the server"
