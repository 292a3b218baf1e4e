#!/usr/bin/env bash
# `make container-test`: build the CPU image and test it the way a user's CI would, with podman.
#  1. docker/Dockerfile.cpu, targets test and runtime (the base: python:3.11-slim where a registry
#     answers, else docker/make-base.sh's; torch: the PyTorch CPU index where it answers, else the
#     wheel the host's pip installs).
#  2. A server container and a test container on a private network, sharing a recordings volume:
#     the test container runs tests/service against the server (OGMAP_SERVER), with ../shared mounted
#     where the tests look for it, so test_real_frames streams 7-Scenes (the synthetic room without it).
#  3. docker/compose.yaml brought up with podman-compose (project ogmap-ct-<pid>, the image built in 1,
#     its three ports published on free host ports): its health check passes, the web view answers on
#     its port, Foxglove accepts a handshake on its port, a client streams a few frames through the gRPC
#     port, the recording and final snapshot land on the compose volume, the server stops gracefully,
#     and `down -v` removes its container and volume.
#  4. deploy/common.yaml + deploy/cpu.yaml played with `podman kube play` on the network of 2: the
#     probe's health check passes, a client streams a few frames, the recording and final snapshot
#     land on the claimed volume, and the pod stops gracefully.
# Exits non-zero on any failure and removes its containers, pod, volumes and networks either way.
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
COMPOSE=(podman-compose -p "$RUN_ID" -f docker/compose.yaml)  # names its resources $RUN_ID_*, labels them
COMPOSE_LABEL="io.podman.compose.project=$RUN_ID"
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
    if [[ -n "${compose_server:-}" ]] && podman container exists "$compose_server"; then
        podman logs "$compose_server" > "$LOGS/compose-server.log" 2>&1 || true
    fi
    compose_remove
    if [[ -n "${kube_played:-}" ]]; then
        kube_manifests | podman kube down - > /dev/null 2>&1 || true
        podman volume rm -f "${KUBE_VOLUMES[@]}" > /dev/null 2>&1 || true
    fi
    podman volume rm -f "$RUN_ID-recordings" > /dev/null 2>&1 || true
    podman network rm -f "$RUN_ID" > /dev/null 2>&1 || true
    if ((status == 0)); then log "passed"; else log "failed (exit $status); logs in $LOGS/"; fi
}
trap cleanup EXIT

compose_remove() {  # the compose project's containers, volumes and network (podman-compose's `down` leaves it)
    podman ps -a -q --filter "label=$COMPOSE_LABEL" 2> /dev/null | xargs -r podman rm -f -v -t 0 > /dev/null 2>&1 || true
    podman volume ls -q --filter "label=$COMPOSE_LABEL" 2> /dev/null | xargs -r podman volume rm -f > /dev/null 2>&1 || true
    podman network ls -q --filter "label=$COMPOSE_LABEL" 2> /dev/null | xargs -r podman network rm -f > /dev/null 2>&1 || true
}

free_ports() {  # count: that many TCP ports free on the host's loopback now
    "${PYTHON:-python3}" -c 'import socket, sys
sockets = [socket.socket() for _ in range(int(sys.argv[1]))]
for one in sockets:
    one.bind(("127.0.0.1", 0))
print(*(one.getsockname()[1] for one in sockets))' "$1"
}

stream_frames() {  # podman run's network flags..., then the server's address: four synthetic frames, closed
    local server=${*: -1}
    podman run --rm "${@:1:$#-1}" --entrypoint ogclient "$TEST_IMAGE" --server "$server" \
        stream --data synthetic --frames 0:4 --scale 0.25 --preset sparse-fast \
        --set keyframes.first_iterations=2 --set keyframes.iterations=1 --close --quiet --session-out /tmp/session.json
}

require_recorded() {  # container, where: its /recordings holds a recording and a final snapshot
    local recorded
    recorded=$(podman exec "$1" ls /recordings)
    [[ "$recorded" == *.mcap*.safetensors* ]] || fail "no recording and final snapshot on $2: $recorded"
}

require_clean_exit() {  # container, what: it stopped (the caller stopped it) with exit status 0
    [[ "$(podman inspect --format '{{.State.ExitCode}}' "$1")" == 0 ]] || fail "$2 did not stop cleanly"
}

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
# --init: the tests' own servers start worker processes; those of a server killed outright pass to PID 1,
# which must reap them (pytest does not: they would stay as zombies, alive to the test that waits for them).
if ! podman run --rm --init --name "$RUN_ID-tests" --network "$RUN_ID" -e OGMAP_SERVER=server:50051 -e OGMAP_RECORD_DIR=/recordings \
    -v "$RUN_ID-recordings:/recordings" "${data_mount[@]}" "$TEST_IMAGE" -q -rs tests/service \
    > "$LOGS/tests.log" 2>&1; then
    tail -60 "$LOGS/tests.log"
    fail "tests/service against the server container"
fi
tail -3 "$LOGS/tests.log"
podman stop -t 30 "$SERVER" > /dev/null
require_clean_exit "$SERVER" "the server"

# The host ports: free ones, not compose.yaml's defaults, which the host may be using.
read -r OGMAP_GRPC_PORT OGMAP_WEB_PORT OGMAP_FOXGLOVE_PORT < <(free_ports 3) && [[ -n "$OGMAP_FOXGLOVE_PORT" ]] ||
    fail "no three free ports on 127.0.0.1 for the compose stage"
export OGMAP_GRPC_PORT OGMAP_WEB_PORT OGMAP_FOXGLOVE_PORT
log "podman-compose -p $RUN_ID -f docker/compose.yaml up (gRPC 127.0.0.1:$OGMAP_GRPC_PORT, web $OGMAP_WEB_PORT, Foxglove $OGMAP_FOXGLOVE_PORT; log $LOGS/compose.log)"
"${COMPOSE[@]}" up -d --no-build > "$LOGS/compose.log" 2>&1 || { tail -20 "$LOGS/compose.log"; fail "podman-compose up"; }
compose_server=$(podman ps -a -q --filter "label=$COMPOSE_LABEL" --filter label=com.docker.compose.service=server)
[[ -n "$compose_server" ]] || { tail -20 "$LOGS/compose.log"; fail "podman-compose up started no server container"; }
compose_server=$(podman inspect --format '{{.Name}}' "$compose_server")
wait_healthy "$compose_server" 300
page=$(curl -sS -m 20 -w '%{http_code}' "http://127.0.0.1:$OGMAP_WEB_PORT/") || fail "the web view does not answer on 127.0.0.1:$OGMAP_WEB_PORT"
[[ "$page" == *"<h1>Maps</h1>"*200 ]] || fail "the web view's / on 127.0.0.1:$OGMAP_WEB_PORT: ${page: -200}"
# A WebSocket handshake offering Foxglove's subprotocol: the server's first message is its serverInfo.
{ curl -sS -N -m 5 -H 'Connection: Upgrade' -H 'Upgrade: websocket' -H 'Sec-WebSocket-Version: 13' \
    -H 'Sec-WebSocket-Key: b2dtYXBwaW5nLXRlc3QtMQ==' -H 'Sec-WebSocket-Protocol: foxglove.sdk.v1' \
    "http://127.0.0.1:$OGMAP_FOXGLOVE_PORT/" 2> /dev/null || true; } | grep -a -q '"op":"serverInfo"' ||
    fail "Foxglove on 127.0.0.1:$OGMAP_FOXGLOVE_PORT: no serverInfo after a WebSocket handshake"
stream_frames --network host "127.0.0.1:$OGMAP_GRPC_PORT"
require_recorded "$compose_server" "the compose volume"
"${COMPOSE[@]}" stop -t 30 >> "$LOGS/compose.log" 2>&1 || fail "podman-compose stop"
require_clean_exit "$compose_server" "the compose server"
podman logs "$compose_server" > "$LOGS/compose-server.log" 2>&1 || true
"${COMPOSE[@]}" down -v >> "$LOGS/compose.log" 2>&1 || fail "podman-compose down -v"
left=$(podman ps -a -q --filter "label=$COMPOSE_LABEL"; podman volume ls -q --filter "label=$COMPOSE_LABEL")
[[ -z "$left" ]] || fail "podman-compose down -v left: $left"
compose_remove  # its network

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
stream_frames --network "$RUN_ID" "$KUBE_POD:50051"
require_recorded "$KUBE_POD-server" "the claimed volume"
podman pod stop -t 60 "$KUBE_POD" > /dev/null
require_clean_exit "$KUBE_POD-server" "the pod"
