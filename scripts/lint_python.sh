#!/usr/bin/env bash
# Python lint gate: ruff over the training pipeline and the ctypes binding.
# Settings: [tool.ruff] in training/pyproject.toml (bindings/python/ruff.toml extends it).
# ruff comes with the `lint` extra (scripts/setup_python.sh). `ruff format` is not used:
# the code keeps its own formatting.
set -euo pipefail
cd "$(dirname "$0")/.."
RUFF=.venv/bin/ruff
if [ ! -x "$RUFF" ]; then
  echo "lint_python.sh: $RUFF not found; run scripts/setup_python.sh first" >&2
  exit 1
fi
"$RUFF" --version
"$RUFF" check training bindings/python
