#!/usr/bin/env bash
# train-vq throughput (windows/s) of this tree against a base commit, in interleaved rounds.
#   BASE=8151c4a ROUNDS=3 DATA=data/sg3000_prep bash scripts/vq_throughput.sh [vq_throughput.py args...]
set -euo pipefail
cd "$(dirname "$0")/.."
BASE=${BASE:-8151c4a} exec bash scripts/ab_bench.sh scripts/vq_throughput.py windows_per_s \
  --data "${DATA:-data/sg3000_prep}" "$@"
