#!/usr/bin/env bash
# Builds the library a host ships: `cargo build --profile plugin` without tract (cargo
# feature `onnx` off; the embedded default runs all three models natively), stripped, whole-
# program optimised. Then checks it as a host would: its size against the <= 40 MB goal
# (LIMIT bytes, default 40,000,000), that it exports the C ABI and links nothing from tract, and
# that a C program linked to it streams a prompt on the embedded default to CG_END.
#   bash scripts/plugin.sh            -> target/plugin/libcomgrasp.{so,a}, ~2-4 min from scratch
# Install it like the release build: scripts/install.sh PREFIX target/plugin
set -euo pipefail
cd "$(dirname "$0")/.."
LIMIT=${LIMIT:-40000000}
target=${CARGO_TARGET_DIR:-target}
cargo build --locked --profile plugin -p comgrasp --lib --no-default-features --features embedded-default
so="$target/plugin/libcomgrasp.so"
size=$(stat -c %s "$so")
echo "plugin: $so is $size bytes (limit $LIMIT)"
if [ "$size" -gt "$LIMIT" ]; then
  echo "plugin: FAIL: larger than $LIMIT bytes" >&2
  exit 1
fi
if ! nm -D --defined-only "$so" | grep -qw cg_start; then
  echo "plugin: FAIL: cg_start is not exported" >&2
  exit 1
fi
# The profile strips symbols, so look for tract's own strings in the data.
if grep -qa "tract_onnx" "$so"; then
  echo "plugin: FAIL: the library still contains tract" >&2
  exit 1
fi

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
cat >"$tmp/smoke.c" <<'EOF'
#include <stdio.h>
#include <time.h>
#include "comgrasp.h"
int main(void) {
    cg_engine_config ecfg; cg_engine_config_init(&ecfg);
    cg_engine *engine; cg_stream *stream; cg_frame frame;
    if (cg_engine_create(&ecfg, &engine) != CG_OK) { printf("create: %s\n", cg_last_error()); return 1; }
    cg_status st = cg_start(engine, "A woman drinks from the mug", NULL, &stream);
    if (st != CG_OK) { printf("start: %s\n", cg_last_error()); return 1; }
    long frames = 0, last = 0;
    while (st == CG_OK) {
        st = cg_poll_frame(stream, &frame);
        if (st == CG_OK) { frames++; last = frame.is_last; }
        else if (st == CG_PENDING) { struct timespec t = {0, 1000000}; nanosleep(&t, NULL); st = CG_OK; }
    }
    printf("%ld frames, last flagged %ld, ended with %s\n", frames, last, cg_status_string(st));
    cg_stream_destroy(stream);
    cg_engine_destroy(engine);
    return (st == CG_END && frames > 16 && last) ? 0 : 1;
}
EOF
cc -O2 -Iinclude "$tmp/smoke.c" -L"$target/plugin" -lcomgrasp -Wl,-rpath,"$(cd "$target/plugin" && pwd)" -o "$tmp/smoke"
"$tmp/smoke"
echo "plugin: OK"
