#!/usr/bin/env bash
# Check docker/Dockerfile.cuda where neither a registry nor a GPU is at hand: build every stage that
# does not need the CUDA images (os, deps, build, deps-test) on a stand-in for the PyTorch runtime
# image, and look inside the result. The stand-in is docker/make-base.sh's Debian base with the host
# pip's torch==2.13.0+cpu in its system Python, where the PyTorch image has its CUDA torch. What this
# cannot build: kernels (nvcc in the devel image), gsplat (its kernels loading against CUDA torch),
# and test and runtime, which copy /opt/gsplat from it. Needs root, podman, debootstrap.
# Logs go to out/cuda-check/. Settings (environment): PYTHON (for the wheel download), CONTAINERS_CONF.
set -euo pipefail
cd "$(dirname "$0")/.."

export CONTAINERS_CONF="${CONTAINERS_CONF:-$PWD/docker/containers.conf}"
LOCAL_BASE=localhost/ogmapping-base:bookworm
STANDIN=localhost/ogmapping-cuda-standin:torch-cpu
TAG=localhost/ogmapping-cuda-check
LOGS=out/cuda-check
started=$SECONDS
mkdir -p "$LOGS"

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
log "passed: os, deps, build, deps-test built and checked; kernels, gsplat, test, runtime need the CUDA images"
