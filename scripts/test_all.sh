#!/usr/bin/env bash
# Install everything and run every test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_python.sh
.venv/bin/python -m pytest training/tests -q -p no:cacheprovider
