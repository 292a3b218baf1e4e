#!/usr/bin/env bash
# GPU benchmark for a bare CUDA machine that has PyTorch but maybe no network (see README.md here).
#
# usage: bench/gpu/run.sh [DATA_DIR] [OUT_DIR]
#   DATA_DIR  7-Scenes folder (default ../shared/data/7scenes-redkitchen)
#   OUT_DIR   where each preset's results go (default bench/gpu/out)
# environment: PRESETS (default "dense sparse sparse-fast"), FRAMES (0:300), SCALE (1.0),
#   PYTHON (python3), SKIP_TESTS=1 to skip the GPU tests.
# Wheels in .whl/ at the repository root are installed into /tmp/site first, without network.
set -euo pipefail
cd "$(dirname "$0")/../.."

DATA=${1:-../shared/data/7scenes-redkitchen}
OUT=${2:-bench/gpu/out}
PRESETS=${PRESETS:-dense sparse sparse-fast}
FRAMES=${FRAMES:-0:300}
SCALE=${SCALE:-1.0}
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1

if compgen -G ".whl/*.whl" >/dev/null; then
    echo "== installing $(ls .whl/*.whl | wc -l) carried wheels into /tmp/site"
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi

echo "== versions"
"$PY" - <<'EOF'
import platform

import torch

print("python", platform.python_version(), "| torch", torch.__version__, "| torch CUDA", torch.version.cuda)
if not torch.cuda.is_available():
    raise SystemExit("no CUDA device visible to PyTorch: this benchmark needs one")
print("GPU", torch.cuda.get_device_name(0), "| capability %d.%d" % torch.cuda.get_device_capability(0))
try:
    import gsplat
    print("gsplat", gsplat.__version__, "at", gsplat.__file__)
except ImportError as error:
    print("gsplat missing:", error)
EOF
command -v nvcc >/dev/null && nvcc --version | tail -n 1 || echo "nvcc not on PATH (gsplat's first use compiles with it)"

# Compile gsplat's kernels now, for this GPU only, so no preset's timing includes the build.
if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then
    TORCH_CUDA_ARCH_LIST=$("$PY" -c "import torch; print('%d.%d' % torch.cuda.get_device_capability(0))")
    export TORCH_CUDA_ARCH_LIST
fi
echo "== gsplat kernels (TORCH_CUDA_ARCH_LIST=$TORCH_CUDA_ARCH_LIST; the first build takes minutes)"
start=$(date +%s)
"$PY" -c "from gsplat.cuda._backend import _C; assert _C is not None, 'gsplat could not build its kernels'"
echo "gsplat kernels ready after $(( $(date +%s) - start )) s"

status=0
if [ "${SKIP_TESTS:-0}" != 1 ]; then
    echo "== GPU tests"
    "$PY" -m pytest -m gpu -ra -q tests/test_gpu_gsplat.py || status=$?
fi

results=()
for preset in $PRESETS; do
    echo "== ogmap run --preset $preset (frames $FRAMES, scale $SCALE)"
    if "$PY" -m ogmapping.cli run --data "$DATA" --frames "$FRAMES" --scale "$SCALE" --device cuda \
        --preset "$preset" --out "$OUT/$preset" --quiet; then
        results+=("$OUT/$preset/results.json")
    else
        status=1
        echo "preset $preset failed"
    fi
done

if [ ${#results[@]} -gt 0 ]; then
    echo "== results"
    "$PY" bench/gpu/table.py "${results[@]}" | tee "$OUT/table.md"
fi
exit $status
