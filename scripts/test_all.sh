#!/usr/bin/env bash
# Install everything and run every test suite (README command 2; CI runs this).
set -euo pipefail
cd "$(dirname "$0")/.."
# System tools (apt, only when missing): cmake, pkg-config, mono (mcs + runtime), python3,
# cc/c++, valgrind; the native-host tests (tests/cmake_package.rs, csharp_binding.rs,
# python_binding.rs) and scripts/sanitize.sh fail without them.
bash scripts/setup_system.sh
# The phases overlap where one of them leaves a core idle (2 cores here; docs/tests.md has
# the timings): a background phase writes its own log, shown in full when it is waited for.
tmp=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$tmp"' EXIT
log=$tmp/summary.log
wait_for() {  # pid, log file, name: fails the run with the phase's log if it failed
  local rc=0
  wait "$1" || rc=$?
  cat "$2"
  if [ "$rc" != 0 ]; then
    echo "test_all: $3 failed (exit $rc)" >&2
    exit "$rc"
  fi
}
# Downloading and unpacking torch (~5 GB) waits on the network and the disk, not the CPU.
(bash scripts/setup_python.sh && bash scripts/setup_node.sh) >"$tmp/setup.log" 2>&1 &
setup=$!
# Lint gates first (a few minutes together; they fail the run before the long suites start):
# formatting (rustfmt.toml), clippy with warnings as errors (allowances: [lints] in
# Cargo.toml, each with its reason), then ruff over training/ and bindings/python.
bash scripts/lint.sh --rust-only
wait_for "$setup" "$tmp/setup.log" "setup_python.sh / setup_node.sh"
bash scripts/lint_python.sh
# pytest alone: beside the test build (2 torch threads + 2 compile jobs on 2 cores) the two
# took longer together (> 15 min) than one after the other (~13 min).
.venv/bin/python -m pytest training/tests -q -p no:cacheprovider 2>&1 | tee -a "$log"
# No doc tests (the crate has none), so the last result line is a real test binary's.
cargo test --locked --lib --bins --tests 2>&1 | tee -a "$log"
# The shipped default's PyTorch parity vectors, replayed by the same tests as models/tiny's;
# and its streams allocation-free (its decoder has the second thread and overlaps the step).
COMGRASP_PARITY_BUNDLE=models/default cargo test --locked --test parity_tiny --test alloc_free_stream 2>&1 | tee -a "$log"
# The library a host ships (no tract, the embedded default deflated): its size against the
# 40 MB goal and a C program streaming a prompt through it (~3 min: its own profile).
bash scripts/plugin.sh
# Issue 8's memory checks. Not tee'd into $log: their indented test summaries are re-runs
# of tests counted above. Either failing exits non-zero here (set -e).
# valgrind + ASan on the C example, valgrind on the C-ABI test binaries (built above): one
# core, so in the background of the fuzz targets' build (libFuzzer + ASan, every target from
# its seed corpus; its own build in fuzz/target, niced).
bash scripts/sanitize.sh >"$tmp/sanitize.log" 2>&1 &
sanitize=$!
fuzz=0
bash scripts/fuzz_smoke.sh 30 || fuzz=$?
wait_for "$sanitize" "$tmp/sanitize.log" sanitize.sh
[ "$fuzz" = 0 ] || exit "$fuzz"
# One closing line over both runners (pytest's "N passed" and cargo's "ok. N passed; M failed").
# awk, not grep, so a count that is absent reads 0 instead of tripping `set -e` under pipefail.
py_line=$(awk '/^[0-9]+ (passed|failed)/ {l=$0} END {print l}' "$log")
py_pass=$(echo "$py_line" | awk '{for (i = 2; i <= NF; i++) if ($i ~ /^passed/) s += $(i-1)} END {print s+0}')
py_fail=$(echo "$py_line" | awk '{for (i = 2; i <= NF; i++) if ($i ~ /^failed/) s += $(i-1)} END {print s+0}')
rs_pass=$(awk '/^test result:/ {s += $4} END {print s+0}' "$log")
rs_fail=$(awk '/^test result:/ {s += $6} END {print s+0}' "$log")
echo "all: $((py_pass + rs_pass)) passed, $((py_fail + rs_fail)) failed"
