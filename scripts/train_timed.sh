#!/usr/bin/env bash
# Train a default model inside a fixed wall-clock allowance on one machine with many cores
# and a GPU (a lent device with minutes to spend, say), then pack the runs' weights small
# enough to carry home; `comgrasp-train export` makes the bundle from them anywhere.
#
# The allowance is spent in overlapping phases, because SynthGrasp generation is CPU work
# (~1 core-second per sequence there before it got 1.3x faster, docs/data.md) and training is GPU work:
#   1. SEQS_VQ sequences (seed 2), prepared without paraphrases: the VQ's data;
#   2. train-vq on them for VQ_SECONDS (--time-budget fits the run and its lr drop to it),
#      while the other cores make the SEQS sequences (seed 1, the recipe's set) with their
#      paraphrases;
#   3. train-gpt on those until the DEADLINE (`--deadline`: its loading, i.e. coding the
#      sequences with the VQ's own normalization and embedding their texts, counts against
#      it), keeping the lowest validation NLL;
#      The Transformers learn on the int8-tok4 text encoder, the one the default bundle
#      embeds (export's --native-text keeps its size; plain int8 adds 5.8 MB);
#   4. the runs without optimizer state (best.pt in fp16, config, stats, logs) ->
#      $PACK/runs.tgz.part-aa, -ab, ... (15 MiB pieces; `cat` joins them), also when a phase
#      failed (the script then exits non-zero).
# Env (defaults: one device command of at most 600 s. The H200 run of 2026-11-27 had
# SEQS=1600 VQ_SECONDS=150 DEADLINE=395, and its GPT memorised its 1,120 training sequences
# after 500 steps. The shipped Transformers learnt from 7,000 of 10,000; SEQS is 5000 because
# that run made 1,600 sequences and their features in 108 s on 14 workers, so 10,000 would
# outlast the VQ's phase (this 2-core CPU makes them 3x faster per core: measure there first);
# docs/training.md):
#   PY=python3 with torch and this package importable; WORK=scratch folder; PACK=output folder
#   SEQS_VQ=800 SEQS=5000 PARAPHRASES=16 WORKERS=$(nproc) WIDTH=0.5
#   VQ_SECONDS=210 VQ_BATCH=64 (x 256 frames) VQ_LR=1e-3 GPT_BATCH=128 GPT_LR=4e-4 DEADLINE=520
#   TEXT_DROPOUT=0.1 (train-gpt --text-dropout: the null condition of classifier-free
#   guidance; choose the bundle's --guidance with scripts/sampling_sweep.py, docs/training.md)
#   bash scripts/train_timed.sh
set -euo pipefail
cd "$(dirname "$0")/.."
START=$(date +%s)
PY=${PY:-.venv/bin/python}
WORK=${WORK:-runs/timed}
PACK=${PACK:-$WORK/pack}
SEQS_VQ=${SEQS_VQ:-800}
SEQS=${SEQS:-5000}
PARAPHRASES=${PARAPHRASES:-16}
WORKERS=${WORKERS:-$(nproc)}
WIDTH=${WIDTH:-0.5}
VQ_SECONDS=${VQ_SECONDS:-210}
VQ_BATCH=${VQ_BATCH:-64}
VQ_LR=${VQ_LR:-1e-3}
GPT_BATCH=${GPT_BATCH:-128}
GPT_LR=${GPT_LR:-4e-4}
TEXT_DROPOUT=${TEXT_DROPOUT:-0.1}
DEADLINE=${DEADLINE:-520}   # seconds after START by which the GPT has stopped
DATA="$PY -m comgrasp_train.cli.data -q"
TRAIN="$PY -m comgrasp_train.cli.train -q"
stamp() { echo "[$(($(date +%s) - START)) s] $*"; }
mkdir -p "$WORK" "$PACK"

stamp "VQ data: $SEQS_VQ sequences"
$DATA synth --out "$WORK/vqdata" --sequences "$SEQS_VQ" --seed 2 --workers "$WORKERS" >/dev/null
$DATA prepare "$WORK/vqdata" --out "$WORK/vqdata_prep" --split synthgrasp --hands --workers "$WORKERS" >/dev/null

stamp "train-vq for $VQ_SECONDS s; meanwhile $SEQS sequences for the Transformers"
# Two cores stay with the trainer: a small-kernel GPU step is bound by its launching thread.
OMP_NUM_THREADS=2 $TRAIN train-vq --data "$WORK/vqdata_prep" --out "$WORK/vq" --preset small \
  --width-scale "$WIDTH" --window 256 --codebook global=1024 --batch "$VQ_BATCH" --lr "$VQ_LR" --lambda-joint 10 \
  --time-budget "$VQ_SECONDS" --ckpt-every 100000 >"$WORK/vq.out" 2>&1 &
VQ_PID=$!
GEN=$((WORKERS > 4 ? WORKERS - 2 : 2))
$DATA synth --out "$WORK/data" --sequences "$SEQS" --seed 1 --workers "$GEN" >/dev/null
$DATA prepare "$WORK/data" --out "$WORK/data_prep" --split synthgrasp --hands --paraphrases "$PARAPHRASES" \
  --workers "$GEN" >/dev/null
stamp "data ready"
RC=0
wait "$VQ_PID" || RC=$?
stamp "VQ done (rc $RC): $(tail -n 1 "$WORK/vq.out")"
if [ "$RC" = 0 ]; then
  stamp "train-gpt until $DEADLINE s"
  $TRAIN train-gpt --data "$WORK/data_prep" --vq "$WORK/vq" --out "$WORK/gpt" --preset small --batch "$GPT_BATCH" \
    --lr "$GPT_LR" --text-weights int8-tok4 --text-dropout "$TEXT_DROPOUT" --deadline "$((START + DEADLINE))" --ckpt-every 100000 >"$WORK/gpt.out" 2>&1 \
    || RC=$?
  stamp "GPT done (rc $RC): $(tail -n 1 "$WORK/gpt.out")"
fi

# Weights alone, in half precision: export rounds them to int8 anyway.
$PY - "$WORK" <<'PY'
import sys
from pathlib import Path

import torch

for f in Path(sys.argv[1]).glob("*/best.pt"):
    ckpt = torch.load(f, map_location="cpu", weights_only=False)
    ckpt["model"] = {k: v.half() if v.is_floating_point() else v for k, v in ckpt["model"].items()}
    torch.save(ckpt, f)
PY
# Only what export needs: no optimizer state, and not the GPT run's cache of codes and text
# embeddings (gpt_cache.py; tens of MB, and remade from the data on a resume).
(cd "$WORK" && tar -cz --exclude=ckpt.pt --exclude='codes_*.npz' --exclude=text_emb.npz $(ls -d vq gpt vq.out gpt.out 2>/dev/null)) | split -b 15m - "$PACK/runs.tgz.part-"
stamp "packed $(du -ch "$PACK"/runs.tgz.part-* | tail -n 1 | cut -f1)"
exit "$RC"
