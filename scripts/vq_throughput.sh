#!/usr/bin/env bash
# train-vq throughput of this tree against a base commit, in interleaved rounds (the
# machines are noisy: never compare runs taken at different times).
#   BASE=8151c4a ROUNDS=3 DATA=data/sg3000_prep bash scripts/vq_throughput.sh [vq_throughput.py args...]
# The base commit is checked out in a temporary worktree; both run scripts/vq_throughput.py
# of this tree with the same arguments. Prints each round and the median ratio.
set -euo pipefail
cd "$(dirname "$0")/.."
BASE=${BASE:-8151c4a}
ROUNDS=${ROUNDS:-3}
DATA=${DATA:-data/sg3000_prep}
wt=$(mktemp -d)
trap 'git worktree remove --force "$wt" >/dev/null 2>&1 || true' EXIT
git worktree add --detach "$wt" "$BASE" >/dev/null 2>&1
run() { PYTHONPATH="$1" .venv/bin/python scripts/vq_throughput.py --data "$DATA" "${@:2}"; }
ratios=()
for r in $(seq "$ROUNDS"); do
  base=$(run "$wt/training/src" "$@")
  head=$(run "$PWD/training/src" "$@")
  echo "round $r base $BASE: $base"
  echo "round $r this tree: $head"
  ratios+=("$(python3 -c "import json,sys; print(json.loads(sys.argv[2])['windows_per_s'] / json.loads(sys.argv[1])['windows_per_s'])" "$base" "$head")")
done
python3 -c "import statistics,sys; r=[float(x) for x in sys.argv[1:]]; print(f'windows/s ratio (this tree / base): median {statistics.median(r):.2f}x, rounds ' + ', '.join(f'{x:.2f}' for x in r))" "${ratios[@]}"
