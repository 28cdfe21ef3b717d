#!/usr/bin/env bash
# Fuzz smoke run (issue 8, point 1): builds the cargo-fuzz targets in fuzz/ once, then runs
# each for SECONDS_PER_TARGET seconds (default 30) starting from its committed seed corpus.
# Exits non-zero if any target crashes, panics, leaks (ASan/LSan), hangs past -timeout or
# fails to build. Crash reproducers land in fuzz/artifacts/<target>/.
#   bash scripts/fuzz_smoke.sh            # ~30 s per target
#   bash scripts/fuzz_smoke.sh 600        # a long run
#   TARGETS="manifest npy" bash scripts/fuzz_smoke.sh 60
#   FUZZ_SANITIZER=none bash scripts/fuzz_smoke.sh     # if ASan is unavailable
#   JOBS=1 bash scripts/fuzz_smoke.sh     # one target at a time (default: as many as cores)
# libFuzzer's closing statistics (execs, cov, ft, corpus) are printed per target and kept in
# target/fuzz-logs/<target>.log.
#
# The stable toolchain runs cargo fuzz with RUSTC_BOOTSTRAP=1 (cargo fuzz passes nightly
# -Z flags: sanitizer, coverage instrumentation). CI=1 keeps the build script from
# rewriting include/comgrasp.h from this (differently configured) build.
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-30}
targets=${TARGETS:-"prompt_text manifest abi_sequence npy"}
sanitizer=${FUZZ_SANITIZER:-address}
export RUSTC_BOOTSTRAP=1 CI=1
# Fuzzing uses every core it is given; stay polite on shared machines.
nice_cmd=(nice -n "${FUZZ_NICE:-10}")

if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "== installing cargo-fuzz"
    # Pinned: the build flags below were chosen for this version.
    "${nice_cmd[@]}" cargo install cargo-fuzz --version 0.13.2 --locked
fi

# The same flags for `build` and `run` (other flags would make `run` rebuild everything).
# --codegen-units 16: cargo fuzz otherwise forces one codegen unit per crate, which peaks at
# 7.2 GB of memory instead of 2.0 (and builds ~30 s slower on 2 cores) for the same exec rate.
# (Build time is mostly set by fuzz/Cargo.toml's profile, see there.)
build_flags=(--sanitizer "$sanitizer" --debug-assertions --codegen-units 16)
echo "== building fuzz targets (sanitizer: $sanitizer, debug assertions on)"
t0=$SECONDS
"${nice_cmd[@]}" cargo fuzz build "${build_flags[@]}"
echo "   built in $((SECONDS - t0)) s"

logs=target/fuzz-logs
mkdir -p "$logs"
# Each target is one single-threaded process: up to JOBS (default: the cores) run at once.
jobs_max=${JOBS:-$(nproc)}
run_target() {  # target -> $logs/<target>.log, and its report in $logs/<target>.result
    local t=$1 scratch result
    scratch=$(mktemp -d)
    local extra=()
    [ -f "fuzz/$t.dict" ] && extra+=("-dict=fuzz/$t.dict")
    # Call sequences need room for many operations (libFuzzer would otherwise start at the
    # seeds' length and grow slowly).
    [ "$t" = abi_sequence ] && extra+=("-max_len=1024")
    # The scratch corpus comes first, so libFuzzer writes its finds there and the committed
    # seeds stay as they are. -timeout: one input running over 30 s is reported as a hang.
    if "${nice_cmd[@]}" cargo fuzz run "${build_flags[@]}" "$t" "$scratch" "fuzz/corpus/$t" -- \
        -max_total_time="$secs" -timeout=30 -rss_limit_mb=4096 -print_final_stats=1 "${extra[@]}" \
        >"$logs/$t.log" 2>&1; then
        result=ok
    else
        result="FAILED (see $logs/$t.log and fuzz/artifacts/$t/)"
    fi
    rm -rf "$scratch"
    # The last status line (#N DONE/pulse cov: .. ft: .. corp: ..) and the final stats.
    local done_line execs rate
    done_line=$(grep -E '^#[0-9]+' "$logs/$t.log" | tail -1 || true)
    execs=$(awk '/stat::number_of_executed_units/ {print $2}' "$logs/$t.log")
    rate=$(awk '/stat::average_exec_per_sec/ {print $2}' "$logs/$t.log")
    {
        echo "== $t: ${secs}s from fuzz/corpus/$t ($(ls "fuzz/corpus/$t" | wc -l) seeds)"
        echo "   $result: ${execs:-?} execs (${rate:-?}/s); $done_line"
        if [ "$result" != ok ]; then
            grep -E 'ERROR|panicked|SUMMARY|deadly signal|Test unit written' "$logs/$t.log" | head -20 || true
        fi
    } >"$logs/$t.result"
}
for t in $targets; do
    rm -f "$logs/$t.result"
    while [ "$(jobs -rp | wc -l)" -ge "$jobs_max" ]; do wait -n || true; done
    run_target "$t" &
done
wait || true
status=0
for t in $targets; do
    if [ -f "$logs/$t.result" ]; then cat "$logs/$t.result"; else echo "== $t: no result (killed?)"; fi
    grep -q '^   ok: ' "$logs/$t.result" 2>/dev/null || status=1
done
if [ $status = 0 ]; then
    echo "fuzz smoke: OK ($(wc -w <<<"$targets") targets, ${secs} s each, $jobs_max at a time)"
else
    echo "fuzz smoke: FAILED"
fi
exit $status
