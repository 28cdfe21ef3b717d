#!/usr/bin/env bash
# Every lint gate (scripts/test_all.sh runs it first): rustfmt --check over the crate and the
# fuzz targets, clippy on every target with warnings as errors (and on the library without
# tract, as scripts/plugin.sh builds it), ruff (scripts/lint_python.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
for tool in rustfmt clippy-driver; do
  if ! command -v "$tool" > /dev/null && ! rustup which "$tool" > /dev/null 2>&1; then
    echo "lint.sh: $tool is missing (rustup component add ${tool%-driver})" >&2
    exit 1
  fi
done
cargo fmt --check
(cd fuzz && cargo fmt --check)
cargo clippy --locked --all-targets -- -D warnings
# The plugin's feature set (no tract, scripts/plugin.sh) compiles other code paths.
cargo clippy --locked -p comgrasp --lib --no-default-features --features embedded-default -- -D warnings
bash scripts/lint_python.sh
echo "lint: rustfmt, clippy and ruff clean"
