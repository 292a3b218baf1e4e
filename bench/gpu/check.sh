#!/usr/bin/env bash
# Everything a short run on a GPU machine should check, in order of value, within a time budget.
#
# usage: bench/gpu/check.sh DATA_DIR RESULTS_TGZ SECONDS
#   DATA_DIR     a 7-Scenes folder holding frames 0-299 (frame-*.color.jpg, *.depth.png, *.pose.txt)
#   RESULTS_TGZ  where to write every log and results.json, packed (rewritten after each step)
#   SECONDS      the budget: a step whose usual cost would overrun it is skipped and said so
# Steps: install (run.sh wheels, then run.sh kernels while the suite runs on CUDA through the pure-torch
# fallback), pytest -m gpu, `run.sh preset` of sparse / sparse-fast / dense on frames 0-299 at 640x480
# and of sparse at 320x240 (to set beside the CPU's figures; results in OUT/640/NAME and OUT/320/NAME),
# the service on CUDA (ogserver + ogclient stream/eval),
# then the suite again with gsplat. A step that succeeded leaves a marker in .gpu/done, so a second
# call on the same warm machine goes on where the first stopped.
# environment: PYTHON (python3), OGMAP_LPIPS_WEIGHTS (LPIPS weights file, optional), FRAMES (0:300).
set -uo pipefail
cd "$(dirname "$0")/../.."
[ $# -eq 3 ] || { sed -n '2,14p' "$0" >&2; exit 2; }
export DATA=$1 TGZ=$2 BUDGET=$3
export PY=${PYTHON:-python3} FRAMES=${FRAMES:-0:300}
export WORK=$PWD/.gpu/out
DONE=$PWD/.gpu/done
mkdir -p "$WORK" "$DONE"
export PYTHONUNBUFFERED=1
export PYTHONPATH=$PWD/.gpu/site:$PWD:$PWD/proto:$PWD/server:$PWD/client
export TORCH_EXTENSIONS_DIR=$PWD/.gpu/torch_extensions

log() { echo "[$(date +%T) +${SECONDS}s] $*" | tee -a "$WORK/check.log"; }
pack() { tar czf "$TGZ" -C "$WORK" . 2>/dev/null; }

# step NAME ESTIMATE_SECONDS FUNCTION [ARGS...]: run once, unless done before or the budget cannot hold
# it; stopped (with every process it started) when the budget runs out.
step() {
    local name=$1 estimate=$2 start=$SECONDS status
    shift 2
    if [ -e "$DONE/$name" ]; then log "$name: done in an earlier call"; return 0; fi
    if (( SECONDS + estimate > BUDGET )); then log "$name: skipped, ${estimate} s would overrun the ${BUDGET} s budget"; return 1; fi
    log "$name: start"
    STEP_LEFT=$((BUDGET - SECONDS)) timeout -s INT -k 15 "$((BUDGET - SECONDS))" bash -c '"$@"' "$name" "$@" \
        >"$WORK/$name.log" 2>&1
    status=$?
    log "$name: exit $status after $((SECONDS - start)) s"
    tail -n 5 "$WORK/$name.log" | sed 's/^/    /' | tee -a "$WORK/check.log"
    [ $status -eq 0 ] && touch "$DONE/$name"
    pack
    return $status
}

# pytest that answers SIGINT with its summary even where the shell started it with SIGINT ignored
# (a background job of a shell without job control).
pytest_interruptible() {
    "$PY" -c 'import signal, sys, pytest; signal.signal(signal.SIGINT, signal.default_int_handler); sys.exit(pytest.main(sys.argv[1:]))' \
        -q -rfE -p no:cacheprovider --timeout 120 --continue-on-collection-errors "$@"
}

# The suite on CUDA: every test whose mapper resolves device "auto" runs on the GPU.
suite() {
    pytest_interruptible -m "not gpu" tests
}

# While gsplat builds, the suite runs through the pure-torch fallback on CUDA; SIGINT at the build's
# end makes pytest print what failed so far.
install_with_fallback_suite() {
    bench/gpu/run.sh wheels || return
    OMP_NUM_THREADS=2 nice -n 19 timeout -s INT "$((STEP_LEFT - 60))" bash -c 'pytest_interruptible "$@"' suite \
        -m "not gpu" tests >"$WORK/suite-torch-fallback.log" 2>&1 &
    local suite_pid=$!
    bench/gpu/run.sh kernels
    local status=$?
    kill -INT "$suite_pid" 2>/dev/null
    wait "$suite_pid"
    return $status
}

service() {
    local port server status
    port=$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
    "$PY" -m ogserver --address "127.0.0.1:$port" --record-dir "$PWD/.gpu/recordings" --device cuda \
        >"$WORK/ogserver.log" 2>&1 &
    server=$!
    for _ in $(seq 120); do
        "$PY" -m ogclient --server "127.0.0.1:$port" list >/dev/null 2>&1 && break
        sleep 1
    done
    "$PY" -m ogclient --server "127.0.0.1:$port" stream --data "$DATA" --frames "$FRAMES" --scale 1 --preset sparse \
        --session-out "$WORK/service-session.json" --quiet &&
        "$PY" -m ogclient --server "127.0.0.1:$port" eval --session "$WORK/service-session.json" --data "$DATA" \
            --frames "$FRAMES" --scale 1 --out "$WORK/service-eval" --quiet
    status=$?
    rm -f "$WORK/service-eval"/*.png
    kill -TERM "$server"
    wait "$server"
    return $status
}

export -f pytest_interruptible suite install_with_fallback_suite service
log "check: budget ${BUDGET} s, data $DATA"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee -a "$WORK/check.log"
step install 420 install_with_fallback_suite || { log "gsplat is not usable: the GPU steps stop here"; pack; exit 1; }
step gpu-tests 45 bench/gpu/run.sh tests
step sparse-640 90 bench/gpu/run.sh preset sparse "$DATA" "$WORK/640"
step sparse-fast-640 60 bench/gpu/run.sh preset sparse-fast "$DATA" "$WORK/640"
SCALE=0.5 step sparse-320 45 bench/gpu/run.sh preset sparse "$DATA" "$WORK/320"
step dense-640 120 bench/gpu/run.sh preset dense "$DATA" "$WORK/640"
step service-sparse-640 120 service
step suite-gsplat 150 suite
log "check: end"
pack
