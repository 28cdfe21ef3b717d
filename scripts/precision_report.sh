#!/usr/bin/env bash
# fp32 vs int8 weights of the default model in one command (issue 7, point 3): the same
# checkpoints evaluated, sampled and benchmarked at both precisions, written to
# $OUT/report.md with the bounds int8 must meet to stay the default.
#   1. an fp32 export of the default checkpoints ($OUT/default_fp32, ~250 MB, ~1.5 min;
#      deleted at the end unless KEEP_FP32=1); the int8 bundle is models/default;
#   2. quality: `comgrasp-train evaluate --rows` without and with --int8-weights (the
#      export's own rounding), held-out SynthGrasp test split, same limit, repeats and seed;
#   3. tokens: scripts/precision_report.py tokens (PyTorch fp32 vs int8: sampled and greedy
#      token streams, logits, distributions along the fp32 tokens, the same tokens through
#      both decoders; the release engine on both bundles, checked against PyTorch);
#   4. speed: `comgrasp bench` on both bundles back to back, and the bundles' sizes.
# About 35 min of CPU (2 x 10 min evaluate, ~10 min tokens; ~1 h wall on a shared 2-core
# machine). Knobs (environment):
#   LIMIT, REPEATS, SEED   evaluate's --limit / --repeats / --seed (default 40, 2, 0)
#   PROMPTS, SEEDS         held-out descriptions and seeds per description for step 3 (50, 2)
#   ENGINE_PROMPTS         prompts run through the engine on both bundles (default 50, 0 = skip)
#   BENCH_ROUNDS           alternating `comgrasp bench` rounds per bundle (default 2; the report
#                          gives their mean)
#   RUN, DATA, INT8, OUT   checkpoints (runs/default), prepared data (data/sg1000_prep), int8
#                          bundle (models/default), output (out/precision)
# Steps whose output exists are skipped (delete the file to redo one).
set -euo pipefail
cd "$(dirname "$0")/.."
P=.venv/bin
LIMIT=${LIMIT:-40}
REPEATS=${REPEATS:-2}
SEED=${SEED:-0}
PROMPTS=${PROMPTS:-50}
SEEDS=${SEEDS:-2}
ENGINE_PROMPTS=${ENGINE_PROMPTS:-50}
BENCH_ROUNDS=${BENCH_ROUNDS:-2}
RUN=${RUN:-runs/default}
DATA=${DATA:-data/sg1000_prep}
INT8=${INT8:-models/default}
OUT=${OUT:-out/precision}
FP32=$OUT/default_fp32
ENGINE=target/release/comgrasp
mkdir -p "$OUT/eval"
[ -x $ENGINE ] || nice cargo build --release --bin comgrasp

# 1. fp32 bundle (only while a step that reads it has not run)
need=0
[ -f $OUT/tokens.json ] || need=1
[ -f $OUT/sizes.json ] || need=1
for r in $(seq 1 "$BENCH_ROUNDS"); do [ -f $OUT/bench_fp32_$r.json ] || need=1; done
[ $need = 0 ] || [ -f $FP32/manifest.json ] || \
  nice $P/comgrasp-train -q export --vq $RUN/vq --gpt $RUN/gpt --out $FP32

# 2. quality
for p in fp32 int8; do
  flag=""; [ $p = int8 ] && flag=--int8-weights
  [ -f $OUT/eval/$p.rows.json ] || nice $P/comgrasp-train -q evaluate --data $DATA --vq $RUN/vq --gpt $RUN/gpt \
    --out $OUT/eval/$p.md --limit "$LIMIT" --repeats "$REPEATS" --seed "$SEED" --device cpu --rows $flag
done

# 3. tokens
engine=(); [ "$ENGINE_PROMPTS" -gt 0 ] && engine=(--engine $ENGINE --engine-prompts "$ENGINE_PROMPTS")
[ -f $OUT/tokens.json ] || nice $P/python scripts/precision_report.py tokens --vq $RUN/vq --gpt $RUN/gpt \
  --data $DATA --int8 "$INT8" --fp32 $FP32 --out $OUT/tokens.json --prompts "$PROMPTS" --seeds "$SEEDS" \
  --seed "$SEED" "${engine[@]}"

# 4. speed: BENCH_ROUNDS rounds of int8 then fp32, back to back, the bench's defaults; and sizes
for r in $(seq 1 "$BENCH_ROUNDS"); do
  for p in int8 fp32; do
    b=$INT8; [ $p = fp32 ] && b=$FP32
    [ -f $OUT/bench_${p}_$r.json ] || nice $ENGINE bench --bundle "$b" --json > $OUT/bench_${p}_$r.json
  done
done
[ -f $OUT/sizes.json ] || $P/python - "$INT8" "$FP32" > $OUT/sizes.json <<'PY'
import json, sys
from pathlib import Path
def size(b, pred=lambda p: True):
    return sum(p.stat().st_size for p in Path(b).rglob("*") if p.is_file() and pred(p.relative_to(b).as_posix()))
step_dec = lambda r: r in ("step.onnx", "decoder.onnx") or r.startswith("native/")
print(json.dumps({k: {"bundle": size(b), "step+decoder files": size(b, step_dec)}
                  for k, b in zip(("int8", "fp32"), sys.argv[1:])}))
PY
$P/python scripts/precision_report.py report --dir $OUT
[ "${KEEP_FP32:-0}" = 1 ] || rm -rf $FP32
