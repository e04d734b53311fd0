# Shared by compare_models.sh and compare_mining.sh (sourced, not run): train a model on the
# benchmark tree for a wall-clock budget unless it exists, and evaluate it on all 4096 points.
# Expects ROOT, MINUTES, OUT, POINTS and CFG to be set.

train() {  # NAME, extra `pnvlad train` options...
    local name=$1; shift
    if [ ! -f "$OUT/$name/model/model.json" ]; then
        pnvlad -q train -c "$CFG" --root "$ROOT" --splits "$ROOT/splits.json" -o "$OUT/$name" \
            --max-minutes "$MINUTES" --num-points "$POINTS" --no-progress "$@" \
            > "$OUT/$name.log" 2>&1
    fi
}

evaluate() {  # NAME
    pnvlad -q eval --checkpoint "$OUT/$1/model" --root "$ROOT" --splits "$ROOT/splits.json" \
        -o "$OUT/$1.json" --num-points 4096 --no-progress
}
