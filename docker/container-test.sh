#!/usr/bin/env bash
# `make container-test`: build the CPU image and test it the way a user's CI would, with podman.
#  1. docker/Dockerfile.cpu, targets test and runtime (the base: python:3.11-slim where a registry
#     answers, else docker/make-base.sh's; torch: the PyTorch CPU index where it answers, else the
#     wheel the host's pip installs).
#  2. A server container and a test container on a private network, sharing a recordings volume:
#     the test container runs tests/service against the server (OGMAP_SERVER), with ../shared mounted
#     where the tests look for it, so test_real_frames streams 7-Scenes (the synthetic room without it).
#  3. deploy/common.yaml + deploy/cpu.yaml played with `podman kube play` on the same network: the
#     probe's health check passes, a client streams a few frames, the recording and final snapshot
#     land on the claimed volume, and the pod stops gracefully.
# Exits non-zero on any failure and removes its containers, pod, volumes and network either way.
# Logs go to out/container-test/. Settings (environment): BASE_IMAGE, TORCH_INDEX_URL, SHARED, PYTHON,
# CONTAINERS_CONF (default docker/containers.conf).
set -euo pipefail
cd "$(dirname "$0")/.."

export CONTAINERS_CONF="${CONTAINERS_CONF:-$PWD/docker/containers.conf}"
IMAGE=localhost/ogmapping:cpu
TEST_IMAGE=localhost/ogmapping:cpu-test
OFFICIAL_BASE=docker.io/library/python:3.11-slim
LOCAL_BASE=localhost/ogmapping-base:bookworm
TORCH_INDEX_URL="${TORCH_INDEX_URL-https://download.pytorch.org/whl/cpu}"
SHARED="${SHARED:-$(cd .. && pwd)/shared}"
LOGS=out/container-test
RUN_ID="ogmap-ct-$$"
SERVER="$RUN_ID-server"
KUBE_POD=ogmapping-pod-0  # deploy/cpu.yaml's Deployment, as podman kube play names its pod
KUBE_VOLUMES=(ogmapping-recordings ogmapping-config)
started=$SECONDS
mkdir -p "$LOGS"

# podman without systemd reports, as errors, that it cannot set timers for health checks (the script
# runs them) and that syslog is absent: left out of the output, every other line is kept.
podman() { command podman "$@" 2> >(grep -v -e 'unable to get systemd connection' -e 'connect to syslog' >&2); }

log() { printf '[container-test %4ss] %s\n' "$((SECONDS - started))" "$*"; }
fail() { log "FAILED: $*"; exit 1; }

kube_manifests() {  # podman 4.3 publishes each containerPort on the host, unlike Kubernetes: not that here
    cat deploy/common.yaml
    sed '/^ *ports:$/{N;/containerPort/d}' deploy/cpu.yaml
}

cleanup() {
    local status=$?
    podman logs "$SERVER" > "$LOGS/server.log" 2>&1 || true
    podman logs "$KUBE_POD-server" > "$LOGS/kube-server.log" 2>&1 || true
    podman rm -f -v -t 0 "$SERVER" > /dev/null 2>&1 || true
    if [[ -n "${kube_played:-}" ]]; then
        kube_manifests | podman kube down - > /dev/null 2>&1 || true
        podman volume rm -f "${KUBE_VOLUMES[@]}" > /dev/null 2>&1 || true
    fi
    podman volume rm -f "$RUN_ID-recordings" > /dev/null 2>&1 || true
    podman network rm -f "$RUN_ID" > /dev/null 2>&1 || true
    if ((status == 0)); then log "passed"; else log "failed (exit $status); logs in $LOGS/"; fi
}
trap cleanup EXIT

wait_healthy() {  # container, seconds
    # Polled with a plain exec: a failed `podman healthcheck run` restarts a kube-played container
    # (its liveness probe) at once. No systemd here to run the checks on a timer; run once when serving.
    local deadline=$((SECONDS + $2))
    until podman exec "$1" python -m ogserver.healthcheck 127.0.0.1:50051 > /dev/null 2>&1; do
        [[ "$(podman inspect --format '{{.State.Running}}' "$1")" == true ]] || { podman logs "$1" | tail -20; fail "$1 exited"; }
        ((SECONDS < deadline)) || { podman logs "$1" | tail -20; fail "$1 not serving after $2 s"; }
        sleep 2
    done
    podman healthcheck run "$1" > /dev/null || fail "$1: its health check (image HEALTHCHECK or liveness probe) fails"
}

choose_base() {
    if [[ -n "${BASE_IMAGE:-}" ]]; then
        return
    elif podman image exists "$OFFICIAL_BASE" || podman pull -q "$OFFICIAL_BASE" > /dev/null 2>&1; then
        BASE_IMAGE=$OFFICIAL_BASE
    else
        log "no registry answers: building the local base ($LOCAL_BASE)"
        BASE_IMAGE=$LOCAL_BASE docker/make-base.sh
        BASE_IMAGE=$LOCAL_BASE
    fi
}

choose_torch() {
    if [[ -n "$TORCH_INDEX_URL" ]] && ! curl -fsS -m 20 -o /dev/null "$TORCH_INDEX_URL/torch/" 2> /dev/null; then
        log "$TORCH_INDEX_URL does not answer: torch from the host's pip"
        TORCH_INDEX_URL=""
    fi
    if [[ -z "$TORCH_INDEX_URL" ]]; then
        "${PYTHON:-python3}" -m pip download --quiet --no-deps --dest docker/wheels "torch==2.13.0+cpu" ||
            fail "the host's pip has no torch==2.13.0+cpu to put in docker/wheels/"
    fi
}

build() {  # target, tag
    log "building $2 (target $1; log $LOGS/build-$1.log)"
    podman build --format docker --network host -f docker/Dockerfile.cpu --target "$1" -t "$2" \
        --build-arg BASE_IMAGE="$BASE_IMAGE" --build-arg TORCH_INDEX_URL="$TORCH_INDEX_URL" . \
        > "$LOGS/build-$1.log" 2>&1 || { tail -30 "$LOGS/build-$1.log"; fail "podman build --target $1"; }
}

choose_base
choose_torch
log "base $BASE_IMAGE, torch from ${TORCH_INDEX_URL:-docker/wheels/}"
replaced=$(podman image inspect --format '{{.Id}}' "$TEST_IMAGE" "$IMAGE" 2>/dev/null || true)
build test "$TEST_IMAGE"
build runtime "$IMAGE"
# The images these builds replaced: removed, so that runs after code changes do not fill the disk.
# (Not `podman image prune`: the untagged stages deps, build and deps-test are the build cache.)
current=$(podman image inspect --format '{{.Id}}' "$TEST_IMAGE" "$IMAGE")
for image in $replaced; do
    [[ "$current" == *"$image"* ]] || podman rmi "$image" > /dev/null 2>&1 || true
done
log "$IMAGE: $(podman image inspect --format '{{.Size}}' "$IMAGE" | numfmt --to=iec) ($TEST_IMAGE: $(podman image inspect --format '{{.Size}}' "$TEST_IMAGE" | numfmt --to=iec))"

podman network create "$RUN_ID" > /dev/null
podman volume create "$RUN_ID-recordings" > /dev/null
data_mount=()
if [[ -d "$SHARED/data" ]]; then
    data_mount=(-v "$SHARED:/opt/shared:ro")  # tests/conftest.py: /opt/ogmapping-tests/tests/../../shared
    log "real frames from $SHARED"
else
    log "$SHARED/data not found: the tests use the synthetic room"
fi

log "server container $SERVER"
podman run -d --name "$SERVER" --network "$RUN_ID" --network-alias server \
    -v "$RUN_ID-recordings:/recordings" -v "$PWD/docker/test-server.yaml:/etc/ogmapping/server.yaml:ro" \
    "$IMAGE" --address 0.0.0.0:50051 --record-dir /recordings --device cpu --config /etc/ogmapping/server.yaml \
    > /dev/null
wait_healthy "$SERVER" 300

log "test container: pytest tests/service against server:50051 (log $LOGS/tests.log)"
if ! podman run --rm --name "$RUN_ID-tests" --network "$RUN_ID" -e OGMAP_SERVER=server:50051 -e OGMAP_RECORD_DIR=/recordings \
    -v "$RUN_ID-recordings:/recordings" "${data_mount[@]}" "$TEST_IMAGE" -q -rs tests/service \
    > "$LOGS/tests.log" 2>&1; then
    tail -60 "$LOGS/tests.log"
    fail "tests/service against the server container"
fi
tail -3 "$LOGS/tests.log"
podman stop -t 30 "$SERVER" > /dev/null
[[ "$(podman inspect --format '{{.State.ExitCode}}' "$SERVER")" == 0 ]] || fail "the server did not stop cleanly"

log "podman kube play deploy/common.yaml deploy/cpu.yaml"
if podman pod exists "$KUBE_POD"; then
    fail "a pod $KUBE_POD exists already: not replacing it"
fi
for volume in "${KUBE_VOLUMES[@]}"; do
    if podman volume exists "$volume"; then
        fail "a volume $volume exists already: not touching it"
    fi
done
kube_played=1
kube_manifests | podman kube play --network "$RUN_ID" - > "$LOGS/kube-play.log" 2>&1 ||
    { cat "$LOGS/kube-play.log"; fail "podman kube play"; }
wait_healthy "$KUBE_POD-server" 300
podman run --rm --network "$RUN_ID" --entrypoint ogclient "$TEST_IMAGE" --server "$KUBE_POD:50051" \
    stream --data synthetic --frames 0:4 --scale 0.25 --preset sparse-fast \
    --set keyframes.first_iterations=2 --set keyframes.iterations=1 --close --quiet --session-out /tmp/session.json
recorded=$(podman exec "$KUBE_POD-server" ls /recordings)
[[ "$recorded" == *.mcap*.safetensors* ]] || fail "no recording and final snapshot on the claimed volume: $recorded"
podman pod stop -t 60 "$KUBE_POD" > /dev/null
[[ "$(podman inspect --format '{{.State.ExitCode}}' "$KUBE_POD-server")" == 0 ]] || fail "the pod did not stop cleanly"
