#!/usr/bin/env bash
# Soak run (not part of CI's default path): 8 concurrent streams through the C ABI,
# restarted until each has generated 10 minutes of motion, with frames/s and resident memory
# printed along the way (examples/soak.rs). Niced, release build.
#   bash scripts/soak.sh                                   # 8 streams x 10 min, embedded default
#   bash scripts/soak.sh --streams 4 --minutes 1 --bundle models/tiny
# Any argument replaces the defaults below (see examples/soak.rs for the options).
set -euo pipefail
cd "$(dirname "$0")/.."
args=("$@")
if [ ${#args[@]} -eq 0 ]; then
    args=(--streams 8 --minutes 10)
fi
nice -n 10 cargo build --locked --release --example soak
exec nice -n 10 target/release/examples/soak "${args[@]}"
