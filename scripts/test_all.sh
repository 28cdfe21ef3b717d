#!/usr/bin/env bash
# Install everything and run every test suite (README command 2; CI runs this).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_python.sh
.venv/bin/python -m pytest training/tests -q -p no:cacheprovider
cargo test --locked
