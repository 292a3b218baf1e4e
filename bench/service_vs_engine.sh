#!/usr/bin/env bash
# The same 7-Scenes frames through the service (ogserver + ogclient stream/eval) and through
# `ogmap run`, to measure the service's throughput overhead and check quality is equal.
# Usage: bench/service_vs_engine.sh [FRAMES=0:300] [SCALE=0.5] [OUT=runs/service] [PRESET=sparse]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-../shared/data/7scenes-redkitchen}
FRAMES=${1:-0:300}
SCALE=${2:-0.5}
OUT=${3:-runs/service}
PRESET=${4:-sparse}
BIN=${BIN:-.venv/bin}
PORT=${PORT:-50777}
mkdir -p "$OUT"
"$BIN/ogserver" --address "127.0.0.1:$PORT" --record-dir "$OUT/recordings" > "$OUT/server.log" 2>&1 &
server=$!
trap 'kill $server 2>/dev/null; wait $server 2>/dev/null' EXIT
for _ in $(seq 60); do "$BIN/python" -m ogserver.healthcheck "127.0.0.1:$PORT" > /dev/null 2>&1 && break; sleep 1; done
client=("$BIN/ogclient" --server "127.0.0.1:$PORT")
start=$(date +%s.%N)
"${client[@]}" stream --data "$DATA" --frames "$FRAMES" --scale "$SCALE" --preset "$PRESET" \
  --session-out "$OUT/session.json" --quiet
end=$(date +%s.%N)
"${client[@]}" stats --session "$OUT/session.json" > "$OUT/stats.txt"
"${client[@]}" eval --session "$OUT/session.json" --data "$DATA" --frames "$FRAMES" --scale "$SCALE" \
  --out "$OUT/eval" --quiet > /dev/null
"${client[@]}" close --session "$OUT/session.json" > /dev/null
kill "$server" && wait "$server" || true  # the engine run below gets the machine to itself
"$BIN/ogmap" run --data "$DATA" --frames "$FRAMES" --scale "$SCALE" --preset "$PRESET" --out "$OUT/engine" \
  --quiet > /dev/null
"$BIN/python" - "$OUT" "$start" "$end" <<'PY'
import json, sys
from pathlib import Path
out, start, end = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
service = json.loads((out / "eval" / "results.json").read_text())
engine = json.loads((out / "engine" / "results.json").read_text())
frames = engine["streamed"]["frames"]
service_fps = frames / (end - start)
print("| path | processing FPS | PSNR streamed / held-out | SSIM streamed / held-out | depth L1 cm streamed / held-out |")
print("|---|---|---|---|---|")
for name, result, fps in (("ogmap run", engine, engine["processing_fps"]), ("ogclient stream -> ogserver", service, service_fps)):
    cells = [" / ".join(f"{result[s][k]:.{d}f}" for s in ("streamed", "heldout")) for k, d in (("psnr", 2), ("ssim", 3), ("depth_l1_cm", 2))]
    print(f"| {name} | {fps:.2f} | " + " | ".join(cells) + " |")
print(f"\nservice throughput overhead: {100 * (engine['processing_fps'] / service_fps - 1):.1f}% "
      f"(client wall time {end - start:.1f} s for {frames} frames, including client start-up)")
PY
