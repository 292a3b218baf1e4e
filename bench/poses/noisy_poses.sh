#!/usr/bin/env bash
# A map made from noisy poses against one made from exact poses, both judged at the exact poses.
# Writes the selected frames' exact trajectory and a copy moved by seeded noise (1 cm per axis, 0.5 degrees
# about a random axis, the first pose exact), maps with the noisy one (`ogmap run --poses noisy.tum
# --eval-poses exact.tum`) and with the data's exact poses, and prints one line per run.
# Usage: bench/poses/noisy_poses.sh DATA FRAMES SCALE [SEED=0] [OUT=runs/poses] [ogmap run flags...]
#   e.g. bench/poses/noisy_poses.sh ../shared/data/replica-room0/data 0:20 0.5 1 runs/poses --set poses.refine=true
# Extra flags go to both runs; FORMAT (default auto), PRESET (default sparse) and PYTHON may be set.
# Paths are taken from the current folder.
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'
  exit 2
fi
DATA=$1 FRAMES=$2 SCALE=$3
SEED=${4:-0}
OUT=${5:-runs/poses}
shift $(( $# < 5 ? $# : 5 ))
PY=${PYTHON:-$(dirname "$0")/../../.venv/bin/python}
FORMAT=${FORMAT:-auto}
PRESET=${PRESET:-sparse}
selection=(--data "$DATA" --format "$FORMAT" --frames "$FRAMES" --scale "$SCALE")
mkdir -p "$OUT"
"$PY" -m ogmapping.cli trajectory "${selection[@]}" --quiet --out "$OUT/exact.tum"
"$PY" -m ogmapping.cli trajectory "${selection[@]}" --quiet --noise-translation 0.01 --noise-rotation 0.5 \
  --noise-seed "$SEED" --out "$OUT/noisy.tum"
"$PY" -m ogmapping.cli run "${selection[@]}" --preset "$PRESET" --poses "$OUT/noisy.tum" \
  --eval-poses "$OUT/exact.tum" --out "$OUT/noisy_seed$SEED" --quiet "$@" > /dev/null
"$PY" -m ogmapping.cli run "${selection[@]}" --preset "$PRESET" --out "$OUT/exact" --quiet "$@" > /dev/null
"$PY" - "$OUT/noisy_seed$SEED/results.json" "$OUT/exact/results.json" <<'PYTHON'
import json
import sys

def scores(splits: dict) -> str:
    return f"streamed {splits['streamed']['psnr']:.2f} dB, held-out {splits['heldout']['psnr']:.2f} dB"

noisy, exact = (json.load(open(path)) for path in sys.argv[1:])
print(f"noisy poses ({noisy['poses']}): at the exact poses {scores(noisy['at_eval_poses'])}; "
      f"at the noisy poses {scores(noisy)}; {noisy['processing_fps']:.2f} frames/s")
print(f"exact poses: {scores(exact)}; {exact['processing_fps']:.2f} frames/s")
PYTHON
