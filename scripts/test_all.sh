#!/usr/bin/env bash
# Install everything and run every test suite (README command 2; CI runs this).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_python.sh
log=$(mktemp)
trap 'rm -f "$log"' EXIT
.venv/bin/python -m pytest training/tests -q -p no:cacheprovider 2>&1 | tee "$log"
# No doc tests (the crate has none), so the last result line is a real test binary's.
cargo test --locked --lib --bins --tests 2>&1 | tee -a "$log"
# One closing line over both runners (pytest's "N passed" and cargo's "ok. N passed; M failed").
py_line=$(grep -E '^[0-9]+ (passed|failed)' "$log" | tail -1 || true)
py_pass=$(echo "$py_line" | grep -Eo '[0-9]+ passed' | awk '{s+=$1} END {print s+0}')
py_fail=$(echo "$py_line" | grep -Eo '[0-9]+ failed' | awk '{s+=$1} END {print s+0}')
rs_pass=$(grep -Eo 'test result: [a-zA-Z]+\. [0-9]+ passed' "$log" | awk '{s+=$4} END {print s+0}')
rs_fail=$(grep -Eo '[0-9]+ failed;' "$log" | awk '{s+=$1} END {print s+0}')
echo "all: $((py_pass + rs_pass)) passed, $((py_fail + rs_fail)) failed"
