#!/usr/bin/env bash
# One Python benchmark of this tree against a base commit, in interleaved rounds (the
# machines are noisy: never compare runs taken at different times).
#   BASE=2732178 ROUNDS=3 bash scripts/ab_bench.sh SCRIPT METRIC [SCRIPT's args...]
# SCRIPT (of this tree) prints one JSON line whose METRIC is higher-is-better; it imports
# whichever comgrasp_train is first on PYTHONPATH: the base commit's, checked out in a
# temporary worktree, then this tree's. Prints each round and the median ratio.
set -euo pipefail
cd "$(dirname "$0")/.."
BASE=${BASE:-2732178}
ROUNDS=${ROUNDS:-3}
script=$1 metric=$2
shift 2
wt=$(mktemp -d)
trap 'git worktree remove --force "$wt" >/dev/null 2>&1 || true' EXIT
git worktree add --detach "$wt" "$BASE" >/dev/null 2>&1
run() { PYTHONPATH="$1" .venv/bin/python "$script" "${@:2}" | tail -n 1; }
ratios=()
for r in $(seq "$ROUNDS"); do
  base=$(run "$wt/training/src" "$@")
  head=$(run "$PWD/training/src" "$@")
  echo "round $r base $BASE: $base"
  echo "round $r this tree: $head"
  ratios+=("$(python3 -c "import json,sys; print(json.loads(sys.argv[2])[sys.argv[3]] / json.loads(sys.argv[1])[sys.argv[3]])" "$base" "$head" "$metric")")
done
python3 -c "import statistics,sys; r=[float(x) for x in sys.argv[2:]]; print(f'{sys.argv[1]} ratio (this tree / base): median {statistics.median(r):.2f}x, rounds ' + ', '.join(f'{x:.2f}' for x in r))" "$metric" "${ratios[@]}"
