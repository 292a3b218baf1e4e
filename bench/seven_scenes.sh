#!/usr/bin/env bash
# `ogmap run` on the 7-Scenes frames for each preset, then one table (bench/table.py).
# Usage: bench/seven_scenes.sh [FRAMES=0:300] [SCALE=0.5] [OUT=runs/bench] [PRESETS="sparse sparse-fast dense"]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-../shared/data/7scenes-redkitchen}
FRAMES=${1:-0:300}
SCALE=${2:-0.5}
OUT=${3:-runs/bench}
PRESETS=${PRESETS:-sparse sparse-fast dense}
PY=${PYTHON:-.venv/bin/python}
folders=()
for preset in $PRESETS; do
  folder="$OUT/${preset}_${FRAMES/:/-}_x${SCALE}"
  "$PY" -m ogmapping.cli run --data "$DATA" --frames "$FRAMES" --scale "$SCALE" --preset "$preset" \
    --out "$folder" --quiet > /dev/null
  folders+=("$folder")
done
"$PY" bench/table.py "${folders[@]}"
