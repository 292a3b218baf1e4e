#!/usr/bin/env bash
# Check docker/Dockerfile.cuda where neither a registry nor a GPU is at hand. The stand-in for the
# PyTorch runtime image is docker/make-base.sh's Debian base with the host pip's torch==2.13.0+cpu in
# its system Python, where the PyTorch image has its CUDA torch.
#  1. The stages that need no CUDA image (os, deps, build, deps-test), built as written on the
#     stand-in, and looked into.
#  2. test and runtime, built from a copy of the Dockerfile (docker/cuda-assembly.py) whose two
#     CUDA-only steps are replaced: kernels copies gsplat's pure-Python wheel instead of compiling one,
#     and the gsplat stage prints why gsplat cannot render instead of requiring that it can. The
#     runtime image then serves on the CPU, passes its health check and stops cleanly.
# What this cannot check: the kernels build (nvcc, the devel image) and their loading (CUDA torch).
# Needs root, podman, debootstrap. Logs go to out/cuda-check/. Settings (environment): PYTHON (for
# the wheel downloads), CONTAINERS_CONF (default docker/containers.conf).
set -euo pipefail
cd "$(dirname "$0")/.."

export CONTAINERS_CONF="${CONTAINERS_CONF:-$PWD/docker/containers.conf}"
LOCAL_BASE=localhost/ogmapping-base:bookworm
STANDIN=localhost/ogmapping-cuda-standin:torch-cpu
TAG=localhost/ogmapping-cuda-check
LOGS=out/cuda-check
started=$SECONDS
mkdir -p "$LOGS"

# podman without systemd reports, as errors, that it cannot set timers for health checks: left out.
podman() { command podman "$@" 2> >(grep -v -e 'unable to get systemd connection' -e 'connect to syslog' >&2); }
log() { printf '[cuda-check %4ss] %s\n' "$((SECONDS - started))" "$*"; }

BASE_IMAGE=$LOCAL_BASE docker/make-base.sh
"${PYTHON:-python3}" -m pip download --quiet --no-deps --dest docker/wheels "torch==2.13.0+cpu"

log "stand-in $STANDIN: $LOCAL_BASE + torch==2.13.0+cpu in the system Python (log $LOGS/build-standin.log)"
podman build --format docker --network host -t "$STANDIN" -f - . > "$LOGS/build-standin.log" 2>&1 <<EOF ||
FROM $LOCAL_BASE
RUN --mount=type=bind,source=docker/wheels,target=/wheels \\
    python3 -m venv /tmp/pip && /tmp/pip/bin/pip install --no-cache-dir --find-links /wheels \\
        --target /usr/local/lib/python3.11/dist-packages "torch==2.13.0+cpu" && rm -rf /tmp/pip
EOF
    { tail -30 "$LOGS/build-standin.log"; exit 1; }

for target in build deps-test; do
    log "Dockerfile.cuda --target $target (log $LOGS/build-$target.log)"
    podman build --format docker --network host -f docker/Dockerfile.cuda --target "$target" -t "$TAG:$target" \
        --build-arg RUNTIME_IMAGE="$STANDIN" --build-arg DEVEL_IMAGE="$STANDIN" . \
        > "$LOGS/build-$target.log" 2>&1 || { tail -30 "$LOGS/build-$target.log"; exit 1; }
done

log "inside $TAG:build"
podman run --rm --entrypoint sh "$TAG:build" -c '
    set -e
    python -c "import sys, torch, gsplat" 2> /dev/null && { echo "gsplat is installed: deps should have removed it"; exit 1; }
    python -c "import jaxtyping, rich, ninja, foxglove, ogmapping, ogserver, ogclient, ogapi; import torch; print(\"torch\", torch.__version__, \"from\", torch.__file__)"
    mkdir /opt/gsplat  # as the gsplat stage makes it: the venv'"'"'s gsplat.pth then puts it on sys.path
    python -c "import sys; assert \"/opt/gsplat\" in sys.path and \"/opt/ogmapping\" in sys.path, sys.path"
    pip list --path "$(python -c "import sysconfig; print(sysconfig.get_path(\"purelib\"))")" 2> /dev/null | tail -n +3 | wc -l | xargs echo "packages in the venv:"
    ogserver --help > /dev/null && ogclient --help > /dev/null
    du -sh /opt/numba-cache
    python -c "from ogmapping.warmup import warm_up; print(\"warm-up on the CPU with the cached kernels:\", round(warm_up(), 1), \"s\")"
    id ogmap'

# Then test and runtime, assembled as on a GPU host but around gsplat's pure-Python wheel: a copy of
# Dockerfile.cuda whose kernels stage copies that wheel instead of compiling one and whose gsplat stage
# prints unavailable_reason() instead of requiring None. Everything else in those stages is as written.
"${PYTHON:-python3}" -m pip download --quiet --no-deps --dest docker/wheels "gsplat==1.5.3"
python3 docker/cuda-assembly.py docker/Dockerfile.cuda > "$LOGS/Dockerfile.assembly"
for target in test runtime; do
    log "assembly: --target $target (log $LOGS/build-assembly-$target.log)"
    podman build --format docker --network host -f "$LOGS/Dockerfile.assembly" --target "$target" \
        -t "$TAG:assembly-$target" --build-arg RUNTIME_IMAGE="$STANDIN" --build-arg DEVEL_IMAGE="$STANDIN" . \
        > "$LOGS/build-assembly-$target.log" 2>&1 || { tail -30 "$LOGS/build-assembly-$target.log"; exit 1; }
done

log "assembly: the runtime image serves on the CPU (--image-volume ignore: no volume is created)"
SERVER="ogmap-cuda-check-$$"
trap 'podman rm -f -t 0 "$SERVER" > /dev/null 2>&1 || true' EXIT
podman run -d --name "$SERVER" --image-volume ignore "$TAG:assembly-runtime" \
    --address 0.0.0.0:50051 --record-dir /recordings --device cpu > /dev/null
deadline=$((SECONDS + 300))
until podman exec "$SERVER" python -m ogserver.healthcheck 127.0.0.1:50051 > /dev/null 2>&1; do
    [[ "$(podman inspect --format '{{.State.Running}}' "$SERVER")" == true ]] || { podman logs "$SERVER" | tail -20; exit 1; }
    ((SECONDS < deadline)) || { podman logs "$SERVER" | tail -20; exit 1; }
    sleep 2
done
podman healthcheck run "$SERVER" > /dev/null || { echo "the image's health check fails"; exit 1; }
podman inspect --format 'user {{.Config.User}}, health check {{.Config.Healthcheck.Test}}' "$SERVER"
podman exec "$SERVER" sh -c 'id -un; ls -ld /recordings /opt/gsplat/gsplat; for c in cc gcc g++; do command -v $c; done; true'
podman logs "$SERVER" 2>&1 | grep -i -e "warming up" -e listening
podman exec "$SERVER" python -c "from ogmapping.render.gsplat_backend import unavailable_reason as why; print('gsplat:', why())"
podman stop -t 30 "$SERVER" > /dev/null
[[ "$(podman inspect --format '{{.State.ExitCode}}' "$SERVER")" == 0 ]] || { echo "the server did not stop cleanly"; exit 1; }

log "assembly: the test image's default command (no GPU: its tests skip)"
podman run --rm "$TAG:assembly-test" 2>&1 | tail -3
for image in build deps-test assembly-test assembly-runtime; do
    echo "$TAG:$image $(podman image inspect --format '{{.Size}}' "$TAG:$image" | numfmt --to=si)"
done
log "passed: os, deps, build, deps-test as written; test and runtime around gsplat's pure-Python wheel; kernels and the gsplat stage's kernel check need the CUDA images"
