#!/usr/bin/env bash
# Every lint gate (scripts/test_all.sh runs it first): rustfmt --check over the crate and the
# fuzz targets, clippy on every target with warnings as errors (and on the library without
# tract, as scripts/plugin.sh builds it), ruff (scripts/lint_python.sh).
#   bash scripts/lint.sh              # all of them
#   bash scripts/lint.sh --rust-only  # no ruff (CI runs it while .venv is still being made)
set -euo pipefail
cd "$(dirname "$0")/.."
rust_only=0
case "${1:-}" in
  "") ;;
  --rust-only) rust_only=1 ;;
  *) echo "usage: $0 [--rust-only]" >&2; exit 2 ;;
esac
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
if [ "$rust_only" = 1 ]; then
  echo "lint: rustfmt and clippy clean"
  exit 0
fi
bash scripts/lint_python.sh
echo "lint: rustfmt, clippy and ruff clean"
