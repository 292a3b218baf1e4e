#!/usr/bin/env bash
# GPU benchmark in steps, each one call that fits a 10-minute limit (see README.md here).
#
# usage: bench/gpu/run.sh install
#        bench/gpu/run.sh wheels
#        bench/gpu/run.sh kernels
#        bench/gpu/run.sh tests
#        bench/gpu/run.sh preset NAME DATA_DIR OUT_DIR
#        bench/gpu/run.sh table OUT_DIR
#   install  carried wheels (.whl/) into .gpu/site, no network; then gsplat's CUDA kernels built for
#            this GPU, with MAX_JOBS (default: the CPU count) parallel compiler jobs
#   wheels   only the carried wheels (the first half of install)
#   kernels  only gsplat's build (the second half of install)
#   tests    pytest -m gpu tests/test_gpu_*.py (gsplat against the pure-torch reference, a mapping step,
#            a frame prepared on the device)
#   preset   ogmap run of one preset (dense, sparse, sparse-fast) on DATA_DIR (7-Scenes unless FORMAT);
#            only its results.json is kept, as OUT_DIR/LABEL/results.json
#   table    OUT_DIR/table.md from OUT_DIR/*/results.json
# environment: FRAMES (0:300), SCALE (1.0), FORMAT (auto), DEVICE (cuda; cpu needs no gsplat),
#   LABEL (the preset's name), STEP_MODE (config step: auto unless set), PYTHON (python3).
# .gpu/ (git-ignored) holds the installed packages and gsplat's build, so later steps on the same
# machine find them without building again.
set -euo pipefail
cd "$(dirname "$0")/../.."

PY=${PYTHON:-python3}
SITE=$PWD/.gpu/site
export PYTHONUNBUFFERED=1
export PYTHONPATH=$SITE:$PWD
export TORCH_EXTENSIONS_DIR=$PWD/.gpu/torch_extensions

usage() {
    sed -n '2,21p' "$0" >&2
    exit 2
}

versions() {
    "$PY" - <<'EOF'
import platform

import torch

print("python", platform.python_version(), "| torch", torch.__version__, "| torch CUDA", torch.version.cuda)
if not torch.cuda.is_available():
    raise SystemExit("no CUDA device visible to PyTorch: this benchmark needs one")
print("GPU", torch.cuda.get_device_name(0), "| capability %d.%d" % torch.cuda.get_device_capability(0))
EOF
    if command -v nvcc >/dev/null; then nvcc --version | tail -n 1; else echo "nvcc not on PATH"; fi
}

gsplat_status() {
    "$PY" -c "from ogmapping.render.gsplat_backend import unavailable_reason as why; r = why(); print(r or 'gsplat usable'); raise SystemExit(r is not None)"
}

wheels() {
    mkdir -p "$SITE"
    if compgen -G ".whl/*.whl" >/dev/null; then
        echo "== installing $(ls .whl/*.whl | wc -l) carried wheels into $SITE"
        "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl
    fi
}

kernels() {
    versions
    mkdir -p "$SITE" .gpu/wheels
    export MAX_JOBS=${MAX_JOBS:-$(nproc)}
    if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then
        TORCH_CUDA_ARCH_LIST=$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability(0))")
        export TORCH_CUDA_ARCH_LIST
    fi
    local start=$SECONDS
    if compgen -G ".whl/gsplat-*.tar.gz" >/dev/null; then
        echo "== building a gsplat wheel from $(ls .whl/gsplat-*.tar.gz) (arch $TORCH_CUDA_ARCH_LIST, MAX_JOBS=$MAX_JOBS)"
        "$PY" -m pip wheel -q --no-deps --no-build-isolation --no-index -w .gpu/wheels .whl/gsplat-*.tar.gz
        "$PY" -m pip install -q --no-index --no-deps --no-compile --upgrade --target "$SITE" .gpu/wheels/gsplat-*.whl
    else
        echo "== gsplat's just-in-time build (arch $TORCH_CUDA_ARCH_LIST, MAX_JOBS=$MAX_JOBS) into $TORCH_EXTENSIONS_DIR"
    fi
    gsplat_status
    echo "gsplat ready after $((SECONDS - start)) s"
}

install() {
    wheels
    kernels
}

tests() {
    gsplat_status
    "$PY" -m pytest -m gpu -ra -q -p no:cacheprovider tests/test_gpu_*.py
}

preset() {
    [ $# -eq 3 ] || usage
    local name=$1 data=$2 out=$3 device=${DEVICE:-cuda} label=${LABEL:-$1} scratch
    [ "$device" = cpu ] || gsplat_status
    scratch=$(mktemp -d)
    trap 'rm -rf "$scratch"' RETURN
    echo "== ogmap run --preset $name on $device (frames ${FRAMES:-0:300}, scale ${SCALE:-1.0}) as $label"
    "$PY" -m ogmapping.cli run --data "$data" --format "${FORMAT:-auto}" --frames "${FRAMES:-0:300}" \
        --scale "${SCALE:-1.0}" --device "$device" --preset "$name" ${STEP_MODE:+--set "step=$STEP_MODE"} \
        --out "$scratch" --quiet
    mkdir -p "$out/$label"
    cp "$scratch/results.json" "$out/$label/results.json"
    "$PY" bench/gpu/table.py "$out/$label"
}

table() {
    [ $# -eq 1 ] || usage
    local out=$1
    compgen -G "$out/*/results.json" >/dev/null || { echo "no results in $out" >&2; exit 1; }
    "$PY" bench/gpu/table.py "$out"/*/results.json | tee "$out/table.md"
}

[ $# -ge 1 ] || usage
step=$1
shift
case $step in
    install) install ;;
    wheels) wheels ;;
    kernels) kernels ;;
    tests) tests ;;
    preset) preset "$@" ;;
    table) table "$@" ;;
    *) usage ;;
esac
