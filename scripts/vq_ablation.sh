#!/usr/bin/env bash
# A short CPU VQ ablation on SynthGrasp (the closing-note run of the model pipeline issue):
# component VQ-VAEs with the causal streaming decoder (ours), with the paper's non-causal
# decoder, and a single VQ-VAE over all 335 features; same data, iterations and widths.
set -euo pipefail
cd "$(dirname "$0")/.."
P=.venv/bin
ITERS=${ITERS:-400}
[ -d data/sg400 ] || $P/comgrasp-data -q synth --out data/sg400 --sequences 400 --seed 0 --workers 2
[ -f data/sg400_prep/stats.npz ] || $P/comgrasp-data -q prepare data/sg400 --out data/sg400_prep --split paper --hands
ARGS="--data data/sg400_prep --preset small --width-scale 0.25 --window 64 --batch 32 --iters $ITERS --lr 4e-4"
$P/comgrasp-train -q train-vq $ARGS --out runs/vq_causal
$P/comgrasp-train -q train-vq $ARGS --out runs/vq_noncausal --paper-decoder
$P/comgrasp-train -q train-vq $ARGS --out runs/vq_single --single
for r in vq_causal vq_noncausal vq_single; do
  $P/comgrasp-train evaluate --data data/sg400_prep --vq runs/$r --out runs/eval_$r/table.md --limit 40
done
