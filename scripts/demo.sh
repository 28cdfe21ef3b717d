#!/usr/bin/env bash
# README command 1: build the engine with its embedded default model and stream one prompt
# into an animated glTF + a PNG preview strip, printing a summary. Needs cargo, and
# libclang for iceoryx2's build (installed with apt by setup_system.sh when missing).
#   bash scripts/demo.sh ["another prompt"]
set -euo pipefail
cd "$(dirname "$0")/.."
TEXT=${1:-"A woman drinks from the mug"}
OUT=out/demo
mkdir -p "$OUT"
bash scripts/setup_system.sh --build-only
cargo build --release --locked --bin comgrasp
target/release/comgrasp generate --text "$TEXT" --glb "$OUT/motion.glb" --preview "$OUT/motion.png" \
  --out "$OUT/motion.json"
echo "open $OUT/motion.glb in Blender (File > Import > glTF 2.0) or https://gltf-viewer.donmccurdy.com"
