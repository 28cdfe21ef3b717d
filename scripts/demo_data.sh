#!/usr/bin/env bash
# The data pipeline on its own: generate SynthGrasp, check it with the metric suite, render
# a sequence (no model involved; see docs/data.md).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_python.sh
OUT=out/demo
P=.venv/bin
rm -rf "$OUT"
$P/comgrasp-data synth --out "$OUT/synthgrasp" --sequences 40 --seed 0 --workers 2
$P/comgrasp-data -q check "$OUT/synthgrasp" --limit 40 --json "$OUT/plausibility.json"
FILE=$(ls "$OUT"/synthgrasp/grab/s*/mug_drink_*.npz 2>/dev/null | head -1 || true)
FILE=${FILE:-$(ls "$OUT"/synthgrasp/grab/s*/*.npz | head -1)}
$P/comgrasp-data text "$FILE" --hands | head -2
$P/comgrasp-data -q render "$FILE" --out "$OUT/sequence.gif"
$P/comgrasp-data -q render "$FILE" --out "$OUT/sequence.png" --strip
echo "demo outputs in $OUT: synthgrasp/, plausibility.json, sequence.gif, sequence.png"
