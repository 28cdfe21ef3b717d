#!/usr/bin/env bash
# Install the Khronos glTF validator (npm package, pinned) into .tools/node, once.
# tests/gltf_output.rs runs tests/gltf/validate.mjs with it on the CLI's .glb output.
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=2.0.0-dev.3.10
PREFIX=.tools/node
PKG="$PREFIX/node_modules/gltf-validator/package.json"
if [ -f "$PKG" ] && grep -q "\"version\": \"$VERSION\"" "$PKG"; then
  exit 0
fi
command -v node >/dev/null || { echo "setup_node: node is not installed" >&2; exit 1; }
command -v npm >/dev/null || { echo "setup_node: npm is not installed" >&2; exit 1; }
mkdir -p "$PREFIX"
npm install --prefix "$PREFIX" --no-audit --no-fund --silent "gltf-validator@$VERSION"
