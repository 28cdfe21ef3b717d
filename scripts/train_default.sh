#!/usr/bin/env bash
# Retrain the embedded default model (models/default) from scratch on SynthGrasp.
# Every stage is skipped when its output exists and every training run resumes from its
# checkpoint, so an interrupted run continues where it stopped when this is run again.
# Sizes are environment variables; the values below are the ones models/default was made
# with (its manifest records the exact configs under provenance).
#   bash scripts/train_default.sh            # CPU or the first CUDA device
set -euo pipefail
cd "$(dirname "$0")/.."
P=.venv/bin
SEQS=${SEQS:-1000}
VQ_ITERS=${VQ_ITERS:-450}
GPT_ITERS=${GPT_ITERS:-2000}
DATA=data/sg$SEQS
RUN=${RUN:-runs/default}
OUT=${OUT:-models/default}
[ -x $P/comgrasp-train ] || bash scripts/setup_python.sh
mkdir -p "$RUN"
[ -f $DATA/synthgrasp_index.json ] || $P/comgrasp-data -q synth --out $DATA --sequences "$SEQS" --seed 1 --workers 2
[ -f ${DATA}_prep/stats.npz ] || $P/comgrasp-data -q prepare $DATA --out ${DATA}_prep --split paper --hands
$P/comgrasp-train -q train-vq --data ${DATA}_prep --out $RUN/vq --preset small \
  --window 64 --batch 32 --iters "$VQ_ITERS" --lr 4e-4 --ckpt-every 50
$P/comgrasp-train -q train-gpt --data ${DATA}_prep --vq $RUN/vq --out $RUN/gpt --preset small \
  --iters "$GPT_ITERS" --batch 64 --lr 3e-4 --ckpt-every 200 --text-weights int8
$P/comgrasp-train evaluate --data ${DATA}_prep --vq $RUN/vq --gpt $RUN/gpt --out $RUN/eval/table.md --limit 60
$P/comgrasp-train export --vq $RUN/vq --gpt $RUN/gpt --out "$OUT" --int8-weights
