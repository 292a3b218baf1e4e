#!/usr/bin/env bash
# The GPU check list, in order of value, within a time budget; a second call goes on where the first stopped.
#
# usage: bench/gpu/check.sh OUT_DIR SECONDS SEVEN_SCENES_DIR [REPLICA_DIR]
#   OUT_DIR           gets results.tgz (bench/gpu/results/DATE-COMMIT/..., to unpack at the repository root),
#                     table.md, check.log and logs.tgz, rewritten after each step
#   SECONDS           the budget: a step whose usual cost would overrun it is skipped and said so
#   SEVEN_SCENES_DIR  7-Scenes RedKitchen (frame-*.depth.png ..., directly or in data/): frames 0-299 for the
#                     640x480 presets and the service's sparse run, 0-99 for the load and CPU thread steps
#   REPLICA_DIR       Replica room0, the folder holding results/ and traj.txt: frames 0-19 at 1200x680
#   A data folder given as - or absent skips the steps that need it, as does one with too few frames.
# Steps: install (carried wheels, gsplat's kernels; the suite runs on CUDA through the pure-torch fallback
# meanwhile), pytest -m gpu, the rasterizer's options and selective Adam timed on one two-view step at 1200x680
# (raster-options: bench/gpu/raster_options.py on the synthetic room, and on Replica room0 where given),
# ogmap run of sparse-fast / sparse / dense on 7-Scenes 0-299 at 640x480 (sparse also with step=dynamic, the
# eager step sized by the data) and on Replica room0 0-19 at 1200x680, sparse with pose refinement from noisy
# poses on room0 (replica-refine), bench/load.py with 1 / 4 / 8 / 16 sparse-fast sessions on one server
# (threads, then 4 worker processes), the service's sparse run of 0-299 (ogserver + ogclient stream/eval), the
# CPU thread table (sparse at 320x240, 1 / 2 / 4 / 8 / 16 threads), sparse at 320x240 on the GPU, the suite
# with gsplat. A step that succeeded leaves a marker in .gpu/done, so a second call on the same machine goes
# on where the first stopped.
# environment: PYTHON (python3), OGMAP_LPIPS_WEIGHTS (LPIPS weights file, optional), COMMIT (default: git's
#   HEAD), STAMP (default: DATE-COMMIT, the results folder's name), ONLY (step names or patterns to run, e.g.
#   "replica-* load"; install runs first where a GPU step needs it), LOAD_FRAMES (0:100), THREAD_FRAMES (0:100),
#   THREADS ("1 2 4 8 16").
set -uo pipefail
cd "$(dirname "$0")/../.."
[ $# -eq 3 ] || [ $# -eq 4 ] || { sed -n '2,25p' "$0" >&2; exit 2; }
OUT=$1 BUDGET=$2 DATA=$3 REPLICA=${4:--}
export PY=${PYTHON:-python3}
export LOAD_FRAMES=${LOAD_FRAMES:-0:100} THREAD_FRAMES=${THREAD_FRAMES:-0:100} THREADS=${THREADS:-1 2 4 8 16}
ONLY=${ONLY:-}
COMMIT=${COMMIT:-$(git rev-parse --short HEAD 2>/dev/null || echo nocommit)}
STAMP=${STAMP:-$(date -u +%F)-$COMMIT}
CHECK=$PWD/.gpu/check
export RESULTS=$CHECK/bench/gpu/results/$STAMP LOGS=$CHECK/logs
DONE=$PWD/.gpu/done
mkdir -p "$OUT" "$RESULTS" "$LOGS" "$DONE/$STAMP"
export DATA REPLICA REPLICA_FRAMES
export PYTHONUNBUFFERED=1
export PYTHONPATH=$PWD/.gpu/site:$PWD:$PWD/proto:$PWD/server:$PWD/client
export TORCH_EXTENSIONS_DIR=$PWD/.gpu/torch_extensions

log() { echo "[$(date +%T) +${SECONDS}s] $*" | tee -a "$LOGS/check.log"; }

pack() {
    "$PY" bench/gpu/table.py --tree "$RESULTS" >"$RESULTS/table.md" 2>>"$LOGS/check.log"
    tar czf "$OUT/results.tgz" -C "$CHECK" bench
    tar czf "$OUT/logs.tgz" -C "$LOGS" .
    cp "$RESULTS/table.md" "$LOGS/check.log" "$OUT/"
}

# frames GLOB DIR...: how many files match GLOB in the first DIR that has any (0 for "-" or absent).
frames() {
    local glob=$1 root count
    shift
    for root in "$@"; do
        count=$(compgen -G "$root/$glob" | wc -l)
        (( count > 0 )) && { echo "$count"; return; }
    done
    echo 0
}
SEVEN_SCENES_FRAMES=$(frames 'frame-*.depth.png' "$DATA" "$DATA/data")
REPLICA_FRAMES=$(frames 'results/depth*.png' "$REPLICA")

# marker NAME: the file that says the step succeeded; install's holds for every commit.
marker() {
    if [ "$1" = install ]; then echo "$DONE/install"; else echo "$DONE/$STAMP/$1"; fi
}

wanted() {
    [ -z "$ONLY" ] && return 0
    local pattern
    for pattern in $ONLY; do
        # shellcheck disable=SC2254 # a pattern on purpose
        case $1 in $pattern) return 0 ;; esac
    done
    return 1
}

# step NAME ESTIMATE_SECONDS NEEDS FUNCTION [ARGS...]: run once, unless done before, not wanted, its data or
# gsplat is missing, or the budget cannot hold it; stopped (with every process it started) when the budget
# runs out. NEEDS: gpu (gsplat usable), 7scenes:N or replica:N (N frames), cpu (nothing); comma-separated.
step() {
    local name=$1 estimate=$2 needs=$3 start=$SECONDS status need
    shift 3
    [ "$name" = install ] || wanted "$name" || return 0
    if [ -e "$(marker "$name")" ]; then log "$name: done in an earlier call"; return 0; fi
    for need in ${needs//,/ }; do
        case $need in
            gpu) [ -e "$(marker install)" ] || { log "$name: skipped, gsplat is not installed (install did not succeed)"; return 1; } ;;
            7scenes:*) (( SEVEN_SCENES_FRAMES >= ${need#*:} )) ||
                { log "$name: skipped, needs 7-Scenes frames 0-$((${need#*:} - 1)); '$DATA' holds $SEVEN_SCENES_FRAMES"; return 1; } ;;
            replica:*) (( REPLICA_FRAMES >= ${need#*:} )) ||
                { log "$name: skipped, needs Replica frames 0-$((${need#*:} - 1)); '$REPLICA' holds $REPLICA_FRAMES"; return 1; } ;;
        esac
    done
    if (( SECONDS + estimate > BUDGET )); then log "$name: skipped, ${estimate} s would overrun the ${BUDGET} s budget"; return 1; fi
    log "$name: start"
    STEP_LEFT=$((BUDGET - SECONDS)) timeout -s INT -k 15 "$((BUDGET - SECONDS))" bash -c '"$@"' "$name" "$@" \
        >"$LOGS/$name.log" 2>&1
    status=$?
    log "$name: exit $status after $((SECONDS - start)) s"
    tail -n 5 "$LOGS/$name.log" | sed 's/^/    /' | tee -a "$LOGS/check.log"
    [ $status -eq 0 ] && touch "$(marker "$name")"
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
        -m "not gpu" tests >"$LOGS/suite-torch-fallback.log" 2>&1 &
    local suite_pid=$!
    bench/gpu/run.sh kernels
    local status=$?
    kill -INT "$suite_pid" 2>/dev/null
    wait "$suite_pid"
    return $status
}

# pytest -m gpu; the step test's figures (step-time.json, sync-sites.json), the Triton kernels' timings
# (triton-loss.json, triton-decode.json), the frame preparation's on the device (preprocess-device.json) and
# the output go to gpu-tests/.
gpu_tests() {
    set -o pipefail
    mkdir -p "$RESULTS/gpu-tests"
    local data=$DATA
    [ "$data" = - ] && data=
    OGMAP_GPU_REPORT=$RESULTS/gpu-tests OGMAP_GPU_DATA=$data bench/gpu/run.sh tests 2>&1 | tee "$RESULTS/gpu-tests/pytest.txt"
}

# bench/load.py: 1 / 4 / 8 / 16 sessions of sparse-fast at 640x480 on one ogserver --device cuda, its sessions
# as threads (NAME load) or in WORKERS worker processes (NAME load-workers-N).
service_load() {
    set -o pipefail
    local name=load workers=()
    if [ -n "${WORKERS:-}" ]; then name=load-workers-$WORKERS; workers=(--workers "$WORKERS"); fi
    mkdir -p "$RESULTS/load"
    "$PY" bench/load.py --device cuda --data "$DATA" --format 7scenes --frames "$LOAD_FRAMES" --scale 1 \
        --preset sparse-fast --sessions 1 4 8 16 "${workers[@]}" --json "$RESULTS/load/$name.json" \
        | tee "$RESULTS/load/$name.md"
}

service_load_workers() {
    WORKERS=4 service_load
}

# ogmap run of sparse at 320x240 on the CPU, once per thread count: torch's (OMP_NUM_THREADS, MKL_NUM_THREADS)
# and Numba's (NUMBA_NUM_THREADS). A sparse map's own torch calls run on one thread whatever the count
# (ogmapping/runtime/profile.py), so the count reaches the compiled kernels and the evaluation. LPIPS is
# off (a weights path that does not exist): it would only lengthen the runs.
cpu_threads() {
    local count
    for count in $THREADS; do
        OMP_NUM_THREADS=$count MKL_NUM_THREADS=$count NUMBA_NUM_THREADS=$count DEVICE=cpu FORMAT=7scenes \
            FRAMES=$THREAD_FRAMES SCALE=0.5 LABEL=threads-$count OGMAP_LPIPS_WEIGHTS=/nonexistent \
            bench/gpu/run.sh preset sparse "$DATA" "$RESULTS/cpu-320" || return
    done
}

service() {
    local port server status dir=$RESULTS/service/sparse-640
    mkdir -p "$dir"
    port=$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
    "$PY" -m ogserver --address "127.0.0.1:$port" --record-dir "$PWD/.gpu/recordings" --device cuda \
        >"$LOGS/ogserver.log" 2>&1 &
    server=$!
    for _ in $(seq 120); do
        "$PY" -m ogclient --server "127.0.0.1:$port" list >/dev/null 2>&1 && break
        sleep 1
    done
    "$PY" -m ogclient --server "127.0.0.1:$port" stream --data "$DATA" --frames 0:300 --scale 1 --preset sparse \
        --session-out "$LOGS/service-session.json" --quiet &&
        "$PY" -m ogclient --server "127.0.0.1:$port" eval --session "$LOGS/service-session.json" --data "$DATA" \
            --frames 0:300 --scale 1 --out "$dir" --quiet
    status=$?
    rm -f "$dir"/*.png
    kill -TERM "$server"
    wait "$server"
    return $status
}

# Pose refinement on the GPU: sparse on Replica room0 0-19 from the exact trajectory moved by seeded noise
# (seed 0: 1 cm per axis, 0.5 degrees), poses.refine on, judged at the exact poses (at_eval_poses in its
# results.json), at 600x340 and 1200x680, into replica-refine/noisy0-WIDTH/.
replica_refine() {
    local scale width scratch status=0
    scratch=$(mktemp -d)
    for scale in 0.5 1; do
        width=$("$PY" -c "print(round(1200 * $scale))")
        "$PY" -m ogmapping.cli trajectory --data "$REPLICA" --format replica --frames 0:20 --scale "$scale" --quiet \
            --out "$scratch/exact.tum" &&
            "$PY" -m ogmapping.cli trajectory --data "$REPLICA" --format replica --frames 0:20 --scale "$scale" \
                --quiet --noise-translation 0.01 --noise-rotation 0.5 --noise-seed 0 --out "$scratch/noisy.tum" &&
            "$PY" -m ogmapping.cli run --data "$REPLICA" --format replica --frames 0:20 --scale "$scale" \
                --device "${DEVICE:-cuda}" --preset sparse --poses "$scratch/noisy.tum" --eval-poses "$scratch/exact.tum" \
                --set poses.refine=true --out "$scratch/run-$width" --quiet || { status=1; continue; }
        mkdir -p "$RESULTS/replica-refine/noisy0-$width"
        cp "$scratch/run-$width/results.json" "$RESULTS/replica-refine/noisy0-$width/"
        "$PY" bench/gpu/table.py "$RESULTS/replica-refine/noisy0-$width"
    done
    rm -rf "$scratch"
    return $status
}

# bench/gpu/raster_options.py: gsplat's packed, absgrad and antialiased options and selective Adam, each timed on
# one steady two-view step at 1200x680 with the PSNR of its renders against the baseline's: on the synthetic
# room (a map over its whole orbit, 3 M Gaussians, about 0.5 M drawn a view) into raster-options/, and with
# Replica room0 0-19 on room0 (0.5 M Gaussians from those frames, all in view) into raster-options/replica/.
raster_options() {
    "$PY" bench/gpu/raster_options.py --device cuda --out "$RESULTS/raster-options" || return
    if (( REPLICA_FRAMES >= 20 )); then
        "$PY" bench/gpu/raster_options.py --device cuda --data "$REPLICA" --format replica --gaussians 500000 \
            --out "$RESULTS/raster-options/replica"
    fi
}

export -f pytest_interruptible suite install_with_fallback_suite gpu_tests service_load service_load_workers cpu_threads service replica_refine raster_options
log "check: budget ${BUDGET} s, results $STAMP, 7-Scenes '$DATA' ($SEVEN_SCENES_FRAMES frames), Replica '$REPLICA' ($REPLICA_FRAMES frames), only '${ONLY:-all}'"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | tee -a "$LOGS/check.log"

GPU_STEPS=(gpu-tests raster-options 640-sparse-fast 640-sparse 640-sparse-dynamic 640-dense replica-sparse-fast replica-sparse replica-dense replica-refine load
           service-sparse-640 320-sparse suite-gsplat)
for name in "${GPU_STEPS[@]}"; do
    if wanted "$name" && [ ! -e "$(marker "$name")" ]; then
        step install 180 cpu install_with_fallback_suite
        break
    fi
done
# ogmap_run GROUP PRESET ESTIMATE NEED FORMAT FRAMES SCALE DATA_DIR: results.json as RESULTS/GROUP/PRESET/.
ogmap_run() {
    step "$1-$2" "$3" "$4,gpu" env FORMAT="$5" FRAMES="$6" SCALE="$7" bench/gpu/run.sh preset "$2" "$8" "$RESULTS/$1"
}
step gpu-tests 150 gpu gpu_tests
step raster-options 60 gpu raster_options
ogmap_run 640 sparse-fast 60 7scenes:300 7scenes 0:300 1 "$DATA"
ogmap_run 640 sparse 90 7scenes:300 7scenes 0:300 1 "$DATA"
# the same map with the step eager and sized by the data, as before compiled graphs: quality and speed side by side
step 640-sparse-dynamic 90 7scenes:300,gpu env STEP_MODE=dynamic LABEL=sparse-dynamic FORMAT=7scenes FRAMES=0:300 SCALE=1 \
    bench/gpu/run.sh preset sparse "$DATA" "$RESULTS/640"
ogmap_run 640 dense 120 7scenes:300 7scenes 0:300 1 "$DATA"
ogmap_run replica sparse-fast 45 replica:20 replica 0:20 1 "$REPLICA"
ogmap_run replica sparse 45 replica:20 replica 0:20 1 "$REPLICA"
ogmap_run replica dense 60 replica:20 replica 0:20 1 "$REPLICA"
step replica-refine 90 replica:20,gpu replica_refine
step load 240 "7scenes:${LOAD_FRAMES#*:},gpu" service_load
step load-workers-4 240 "7scenes:${LOAD_FRAMES#*:},gpu" service_load_workers
step service-sparse-640 120 7scenes:300,gpu service
# about 1.6 s a frame over the five thread counts, and 40 s of start-up
step cpu-threads $((40 + 16 * (${THREAD_FRAMES#*:} - ${THREAD_FRAMES%:*}) / 10)) "cpu,7scenes:${THREAD_FRAMES#*:}" cpu_threads
ogmap_run 320 sparse 45 7scenes:300 7scenes 0:300 0.5 "$DATA"
step suite-gsplat 150 gpu suite
log "check: end"
pack
