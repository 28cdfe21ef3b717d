#!/usr/bin/env bash
# The default model's quality against issue 15's bars, on PyTorch's output and on the
# engine's own frames, in one command:
#   1. `comgrasp-train evaluate` on the held-out SynthGrasp test subjects: VQ reconstruction,
#      generation from the template prompts and from held-out wordings (grab.paraphrase),
#      REPEATS seeds each -> $OUT/table.md (+ .json);
#   2. the release engine (`comgrasp generate --fk`) on ENGINE_PROMPTS prompts covering every
#      intent and hand mode, SEEDS seeds each, checked by `comgrasp-data check-engine`, with
#      the contact-consistency stage (the default) -> $OUT/engine.json, without it (`--raw`,
#      the model's own frames) -> $OUT/engine_raw.json, and the same meanings in held-out
#      wordings (no training text uses their verbs, subjects or hand phrases), with the
#      stage -> $OUT/engine_held_out.json;
#   3. $OUT/bars.md: each bar, the measured value and whether it is met;
#   4. $OUT/contact.md: issue 17's contact measurements on those frames, raw against the
#      contact stage (scripts/contact_report.py).
# Knobs: RUN (runs/default: vq/ and gpt/), DATA (data/sg3000_prep), BUNDLE (models/default),
# LIMIT (100 test sequences), REPEATS (2), ENGINE_PROMPTS (24), SEEDS (2), OUT (out/quality),
# GUIDANCE (the bundle's own `sampling.guidance`, 1 without it: PyTorch samples as the
# engine does), ENGINE_ONLY (0; 1 skips step 1, for a bundle without its checkpoints or data: the bars
# PyTorch measures then come from TABLE, marked so, else read "not measured"), TABLE (the bundle's
# earlier PyTorch table: ${BUNDLE}_eval/table.json).
set -euo pipefail
cd "$(dirname "$0")/.."
P=.venv/bin
RUN=${RUN:-runs/default}
DATA=${DATA:-data/sg3000_prep}
BUNDLE=${BUNDLE:-models/default}
LIMIT=${LIMIT:-100}
REPEATS=${REPEATS:-2}
ENGINE_PROMPTS=${ENGINE_PROMPTS:-24}
SEEDS=${SEEDS:-2}
OUT=${OUT:-out/quality}
mkdir -p "$OUT/engine"
[ -x $P/comgrasp-train ] || bash scripts/setup_python.sh
if [ "${ENGINE_ONLY:-0}" = 0 ] && [ ! -f "$OUT/table.json" ]; then
  GUIDANCE=${GUIDANCE:-$($P/python -c 'import json, sys
print(json.load(open(sys.argv[1])).get("sampling", {}).get("guidance", 1.0))' "$BUNDLE/manifest.json")}
  $P/comgrasp-train -q evaluate --data "$DATA" --vq "$RUN/vq" --gpt "$RUN/gpt" --out "$OUT/table.md" \
    --limit "$LIMIT" --repeats "$REPEATS" --prompts template,held_out --guidance "$GUIDANCE"
fi
[ -x target/release/comgrasp ] || cargo build --release --locked
# run: the contact stage (default) or raw frames; set: the prompts or their held-out wordings
for run in stage:prompts raw:prompts stage:held-out; do
  mode=${run%%:*} set=${run#*:}
  results=()
  k=0
  while IFS=$'\t' read -r prompt meaning; do
    k=$((k + 1))
    for s in $(seq "$SEEDS"); do
      f="$OUT/engine/$([ $set = prompts ] && echo p || echo h)${k}_s${s}_$mode.npz"
      target/release/comgrasp generate --bundle "$BUNDLE" --text "$prompt" --seed "$s" --fk \
        $([ $mode = raw ] && echo --raw) --out "$f" >/dev/null
      $P/comgrasp-data check-engine "$f" --prompt "$prompt" --meaning "$meaning" --json "$f.json" >/dev/null
      results+=("$f.json")
    done
  done < <($P/python scripts/quality_report.py "$set" "$ENGINE_PROMPTS")
  $P/python - "$OUT/engine$([ $mode = raw ] && echo _raw)$([ $set = held-out ] && echo _held_out).json" \
    "${results[@]}" <<'PY'
import json, sys
rows = [r for f in sys.argv[2:] for r in json.load(open(f))["results"]]
keys = sorted({k for r in rows for k in r if k.startswith("intent_")})
rates = {k: sum(r[k] for r in rows if k in r) / max(1, sum(k in r for r in rows)) for k in keys}
json.dump({"rates": rates, "n": len(rows), "results": rows}, open(sys.argv[1], "w"), indent=1)
PY
done
TABLE=${TABLE:-${BUNDLE%/}_eval/table.json}
$P/python scripts/quality_report.py bars "$OUT" "$TABLE"
$P/python scripts/quality_report.py prompts "$ENGINE_PROMPTS" > "$OUT/prompts.tsv"
$P/python scripts/contact_report.py "$OUT/prompts.tsv" "$OUT/engine" | tee "$OUT/contact.md"
