#!/usr/bin/env bash
# Memory-safety checks of the C ABI (issue 8, point 2). Zero errors and zero leaks required.
#
#   bash scripts/sanitize.sh              # valgrind + ASan on the C example, valgrind on the
#                                         # C-ABI test binaries and the pure-Rust unit tests
#   bash scripts/sanitize.sh --miri       # also `cargo miri` where a Miri toolchain exists
#   bash scripts/sanitize.sh --miri-only  # only that (SKIPPED, exit 0, without the toolchain)
#   SANITIZE_SKIP_VALGRIND_TESTS=1 ...    # only the C example (fast)
#
# 1. valgrind memcheck on examples_c/stream.c (built against this checkout's libcomgrasp.so,
#    streaming a prompt on models/tiny to its end) and on the test binaries of every
#    tests/ffi_*.rs, tests/engine_api.rs and tests/soak_fault.rs (scripted sources, the tiny
#    bundle), plus the library's own unit tests of the handle registry, the C configs and
#    frame assembly. Options: --error-exitcode=99 --leak-check=full
#    --errors-for-leak-kinds=definite,indirect (still-reachable and possibly-lost blocks at
#    exit are threads of the runtime, rayon's pool, and process-lifetime statics, not leaks).
#    scripts/valgrind.supp holds the suppressions, each with the reason it exists.
#    The test binaries come from the normal `cargo test` build (no second build of tract).
# 2. AddressSanitizer + LeakSanitizer on the C example: compiled with -fsanitize=address
#    (clang, else gcc); ASan's allocator replaces malloc for the whole process, so Rust's
#    heap (the system allocator) is checked for double/invalid frees and leaks too, though
#    only the C code's own loads and stores are instrumented. The Rust side's loads and
#    stores are instrumented in the ASan fuzz builds (scripts/fuzz_smoke.sh).
# 3. --miri: `cargo +nightly miri test` on the modules that do not call into tract: the
#    handle registry and config unit tests, frame assembly (src/assemble.rs), the native
#    path's thread team (src/model/native/team.rs: the helper thread, its phases' hand-out
#    and the lifetime erasures) and the step's disjoint output parts (RowUnits), and the
#    ring buffer / stream lifecycle through
#    scripted sources (tests/engine_api.rs, the scripted part of tests/soak_fault.rs).
#    Needs a nightly toolchain (MIRI_TOOLCHAIN, default nightly) with the miri and rust-src
#    components; reported as SKIPPED (never as passed, exit 0) where they are missing.
set -euo pipefail
cd "$(dirname "$0")/.."
miri=0
memcheck=1
for a in "$@"; do
    case "$a" in
        --miri) miri=1 ;;
        --miri-only) miri=1; memcheck=0 ;;
        *) echo "usage: $0 [--miri | --miri-only]" >&2; exit 2 ;;
    esac
done
out=target/sanitize
mkdir -p "$out"
failures=()
note() { printf '%s\n' "$*" | tee -a "$out/summary.txt"; }
: >"$out/summary.txt"

if [ "$memcheck" = 1 ]; then
command -v valgrind >/dev/null || { echo "valgrind is not installed (apt-get install valgrind)" >&2; exit 1; }
supp=(--suppressions=scripts/valgrind.supp)
vg=(valgrind --tool=memcheck --error-exitcode=99 --leak-check=full --errors-for-leak-kinds=definite,indirect
    --show-leak-kinds=definite,indirect --num-callers=30 "${supp[@]}")

# The test binaries of the normal debug test build (tract's crates are optimised even there).
ffi_tests=(engine_api soak_fault)
for f in tests/ffi_*.rs; do ffi_tests+=("$(basename "$f" .rs)"); done
test_args=()
for t in "${ffi_tests[@]}"; do test_args+=(--test "$t"); done
echo "== building the test binaries (cargo test --no-run)"
nice -n 10 cargo test --locked --no-run --lib "${test_args[@]}" --message-format=json >"$out/build.json"
exe_of() {  # the test executable of one target ("comgrasp": the library's unit tests)
    python3 - "$out/build.json" "$1" <<'PY'
import json, sys
for line in open(sys.argv[1]):
    m = json.loads(line)
    if (m.get("reason") == "compiler-artifact" and m["profile"]["test"]
            and m["target"]["name"] == sys.argv[2] and m.get("executable")):
        print(m["executable"])
PY
}
libdir=$(dirname "$(exe_of comgrasp)")
[ -f "$libdir/libcomgrasp.so" ] || { echo "no libcomgrasp.so in $libdir" >&2; exit 1; }

run_vg() {  # name, then the command
    local name=$1; shift
    local log="$out/valgrind-$name.log"
    local t0=$SECONDS rc=0
    "${vg[@]}" --log-file="$log" "$@" >"$out/$name.stdout" 2>&1 || rc=$?
    local summary
    summary=$(grep -h 'ERROR SUMMARY' "$log" | head -1 | sed 's/^==[0-9]*== //')
    # 99 is valgrind's own verdict (--error-exitcode); anything else is the program's.
    if [ "$rc" = 0 ]; then
        note "valgrind $name: OK ($((SECONDS - t0)) s) $summary"
    elif [ "$rc" = 99 ]; then
        note "valgrind $name: MEMORY ERRORS OR LEAKS ($((SECONDS - t0)) s) $summary, see $log"
        grep -E 'Invalid|uninitialised|definitely lost|indirectly lost' "$log" | head -20 || true
        failures+=("valgrind $name")
    else
        note "valgrind $name: the program failed (exit $rc) under valgrind ($((SECONDS - t0)) s); valgrind: $summary; see $out/$name.stdout"
        grep -E 'panicked|^test .* FAILED|test result' "$out/$name.stdout" | head -10 || true
        failures+=("$name (exit $rc under valgrind)")
    fi
    grep -hE 'definitely lost|indirectly lost|All heap blocks' "$log" | head -2 | sed 's/^==[0-9]*==/   /' | tee -a "$out/summary.txt"
}

# --- 1. the C example ------------------------------------------------------------------
cc=${CC:-cc}
echo "== C example (examples_c/stream.c) against $libdir/libcomgrasp.so"
"$cc" -std=c11 -g -O1 -Wall -Wextra -Werror -Iinclude examples_c/stream.c -o "$out/stream" \
    -L"$libdir" -lcomgrasp -Wl,-rpath,"$libdir"
run_vg c_example "$out/stream" models/tiny "A woman drinks from the mug"
grep -E '^(frames|status):' "$out/c_example.stdout" | sed 's/^/   /' || true

# --- 2. the C example under ASan + LSan ---------------------------------------------------
# The first of clang and cc that links with -fsanitize=address: Debian's gcc always can
# (libasan comes with it), clang only with libclang-rt-*-dev, which apt treats as optional.
asan_cc=
for c in ${ASAN_CC:-clang cc}; do
    command -v "$c" >/dev/null || continue
    if "$c" -std=c11 -g -O1 -fsanitize=address -fno-omit-frame-pointer -Iinclude examples_c/stream.c \
        -o "$out/stream-asan" -L"$libdir" -lcomgrasp -Wl,-rpath,"$libdir" 2>"$out/asan-build-$c.log"; then
        asan_cc=$c
        break
    fi
done
if [ -n "$asan_cc" ]; then
    echo "== C example under AddressSanitizer + LeakSanitizer ($asan_cc)"
    t0=$SECONDS
    if ASAN_OPTIONS=detect_leaks=1:abort_on_error=0:halt_on_error=1 \
        "$out/stream-asan" models/tiny "A woman drinks from the mug" >"$out/asan.stdout" 2>"$out/asan.stderr"; then
        note "asan c_example ($asan_cc): OK ($((SECONDS - t0)) s), no ASan or LSan report"
    else
        note "asan c_example ($asan_cc): FAILED, see $out/asan.stderr"
        head -40 "$out/asan.stderr"
        failures+=("asan c_example")
    fi
else
    note "asan c_example: SKIPPED (neither clang nor cc links with -fsanitize=address, see $out/asan-build-*.log)"
fi

# --- 1b. the C-ABI test binaries and the pure-Rust unit tests -----------------------------
if [ -z "${SANITIZE_SKIP_VALGRIND_TESTS:-}" ]; then
    for t in "${ffi_tests[@]}"; do
        exe=$(exe_of "$t")
        echo "== valgrind tests/$t.rs"
        # One test thread: valgrind serialises threads anyway, and the timing-based
        # assertions of the stress tests get the whole (emulated) CPU.
        run_vg "$t" "$exe" --test-threads=1
        grep -h '^test result' "$out/$t.stdout" | sed 's/^/   /' || true
    done
    echo "== valgrind: library unit tests (handle registry, C configs, frame assembly, sampler)"
    run_vg lib_units "$(exe_of comgrasp)" --test-threads=1 ffi:: assemble:: sampler:: skeleton::
    grep -h '^test result' "$out/lib_units.stdout" | sed 's/^/   /' || true
fi

fi  # memcheck

# --- 3. Miri --------------------------------------------------------------------------------
if [ "$miri" = 1 ]; then
    tc=${MIRI_TOOLCHAIN:-nightly}
    # RUSTUP_AUTO_INSTALL=0: a missing toolchain is reported, not downloaded (rustup would
    # otherwise fetch a whole nightly, and CI cannot reach the Rust dist server).
    export RUSTUP_AUTO_INSTALL=0
    if miri_version=$(cargo "+$tc" miri --version 2>&1); then
        echo "== cargo +$tc miri test (no tract: handle registry, configs, frame assembly, thread team, scripted streams)"
        # Handles are integers cast to opaque pointer types and never dereferenced (by
        # design, src/ffi/handle.rs): permissive provenance silences Miri's
        # integer-to-pointer-cast warning for them; every other check stays on.
        export MIRIFLAGS="${MIRIFLAGS:--Zmiri-permissive-provenance}"
        t0=$SECONDS
        if nice -n 10 cargo "+$tc" miri test --no-default-features --lib -- ffi::handle ffi::config assemble:: model::native::team:: model::native::step::tests::row_units >"$out/miri-lib.log" 2>&1 \
            && nice -n 10 cargo "+$tc" miri test --no-default-features --test engine_api >"$out/miri-engine_api.log" 2>&1 \
            && nice -n 10 cargo "+$tc" miri test --no-default-features --test soak_fault >"$out/miri-soak_fault.log" 2>&1; then
            note "miri: OK ($((SECONDS - t0)) s) $(grep -h '^test result' "$out"/miri-*.log | tr '\n' ' ')"
        else
            note "miri: FAILED, see $out/miri-*.log"
            tail -30 "$out"/miri-*.log
            failures+=("miri")
        fi
    else
        note "miri: SKIPPED (no $tc toolchain with the miri component: $(head -1 <<<"$miri_version"))"
    fi
fi

echo "---"
cat "$out/summary.txt"
if [ ${#failures[@]} -gt 0 ]; then
    echo "sanitize: FAILED: ${failures[*]}"
    exit 1
fi
skipped=$(grep -c SKIPPED "$out/summary.txt" || true)
if [ "$skipped" -gt 0 ]; then echo "sanitize: OK ($skipped SKIPPED)"; else echo "sanitize: OK"; fi
