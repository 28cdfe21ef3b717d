#!/usr/bin/env bash
# The benchmark in one command (DESIGN §7): builds the release CLI, makes sure the bundles
# exist under out/bench/, runs `comgrasp bench` (engine, tract) and
# `python -m comgrasp_train.bench` (onnxruntime and PyTorch with/without KV cache) on each,
# in the same run and with the same prompt, seed, length and thread count, and prints
# Markdown tables with the ratios, the memory read bandwidth and whether the tokens agree.
#
#   scripts/bench.sh                      # tiny, small and paper bundles, 1 thread
#   BUNDLES="tiny small" scripts/bench.sh # skip the paper-size bundle (~2 GB, ~10 GB RAM to export)
#   THREADS="1 2" scripts/bench.sh        # each bundle at 1 and at 2 threads
#   STEPS=16 scripts/bench.sh             # shorter sequences (default: each bundle's L_max)
#   FEATURES=multithread-mm scripts/bench.sh  # tract's rayon executor, so the engine's
#                                         # --threads applies (needs that crate feature)
#
# Bundles: tiny = models/tiny (committed); small and paper = random weights exported by
# `python -m comgrasp_train.export.random_bundle` into out/bench/<name> (once; delete the
# directory to re-export), with their PyTorch weights in out/bench/<name>_torch.pt.
# Results: out/bench/<name>.t<threads>.{engine,python}.json and out/bench/report.md.
# Timings depend on the machine and on whatever else runs on it; nothing here asserts any.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PY:-.venv/bin/python}
OUT=${OUT:-out/bench}
BUNDLES=${BUNDLES:-"tiny small paper"}
THREADS=${THREADS:-1}
STEPS=${STEPS:-}
PROMPT=${PROMPT:-"A woman drinks from the mug."}
SEED=${SEED:-7}
FEATURES=${FEATURES:-}
BIN=target/release/comgrasp

cargo build --release --locked --bin comgrasp ${FEATURES:+--features "$FEATURES"}
mkdir -p "$OUT"

bundle_dir() {
    case "$1" in
        tiny) echo models/tiny ;;
        *) echo "$OUT/$1" ;;
    esac
}

for name in $BUNDLES; do
    dir=$(bundle_dir "$name")
    if [[ ! -f "$dir/manifest.json" ]]; then
        case "$name" in
            small|paper)
                echo "== exporting the random $name bundle to $dir" >&2
                "$PY" -m comgrasp_train.export.random_bundle --preset "$name" --out "$dir" >&2 ;;
            *) echo "no bundle $dir" >&2; exit 1 ;;
        esac
    fi
done

specs=()
for name in $BUNDLES; do
    dir=$(bundle_dir "$name")
    for t in $THREADS; do
        base="$OUT/$name.t$t"
        args=(--bundle "$dir" --prompt "$PROMPT" --seed "$SEED" --threads "$t")
        [[ -n "$STEPS" ]] && args+=(--steps "$STEPS")
        echo "== $name, $t thread(s): engine" >&2
        "$BIN" bench "${args[@]}" --json > "$base.engine.json"
        echo "== $name, $t thread(s): onnxruntime + PyTorch" >&2
        "$PY" -m comgrasp_train.bench "${args[@]}" --out "$base.python.json" >&2
        specs+=("$name (t$t)=$base.engine.json,$base.python.json")
    done
done

{
    echo "# ComGrasp benchmark"
    echo
    echo "Machine: $(lscpu | sed -n 's/^Model name: *//p') ($(nproc) logical CPUs, $(lscpu | sed -n 's/^L3 cache: *//p') L3), $(free -g | awk '/^Mem:/ {print $2}') GiB RAM; $(date -u +%Y-%m-%dT%H:%MZ)."
    echo "Prompt \"$PROMPT\", seed $SEED, End forbidden before and forced after the step count (same length in every runtime)."
    echo
    "$PY" -m comgrasp_train.bench --table "${specs[@]}"
} | tee "$OUT/report.md"
