"""Helpers of scripts/quality_report.sh.

    python scripts/quality_report.py prompts N       N canonical prompts covering every SynthGrasp
                                                     intent and hand mode (tab: prompt, then meaning)
    python scripts/quality_report.py held-out N      the same meanings in held-out wordings (verbs,
                                                     subjects and hand phrases no training text uses)
    python scripts/quality_report.py bars OUT [TABLE]
                                                     OUT/bars.md from OUT/table.json, OUT/engine.json and OUT/engine_raw.json;
                                                     without OUT/table.json, PyTorch's rows from TABLE (an
                                                     earlier table.json of the same bundle), marked so
"""

from __future__ import annotations

import json
import random
import sys
from pathlib import Path

from comgrasp_train.grab.paraphrase import Meaning, mode_contact, one
from comgrasp_train.grab.text import describe
from comgrasp_train.synth.generate import combinations

# Issue 15's bars: (label, table row prefix, key, comparison, bound)
# Generation bars read the contact stage's rows where the table has them (the engine streams
# through the stage), else the raw ones; each row prefix in order of preference.
_GEN = ("generation, contact stage (", "generation (")
_HELD_OUT = ("generation, held-out prompts, contact stage (", "generation, held-out prompts (")
BARS = (
    ("VQ reconstruction MPJPE (mm)", ("VQ reconstruction",), "mpjpe_mm", "<=", 15.0),
    ("VQ reconstruction H-MPJPE (mm)", ("VQ reconstruction",), "h_mpjpe_mm", "<=", 20.0),
    ("VQ reconstruction contact accuracy", ("VQ reconstruction",), "contact_accuracy", ">=",
     0.98),
    ("generation intent_ok, template prompts", _GEN, "intent_ok", ">=", 0.90),
    ("generation intent_ok, held-out prompts", _HELD_OUT, "intent_ok", ">=", 0.80),
    ("generation: the named hand grasps", _GEN, "intent_grasp", ">=", 0.95),
    ("generation contact F1", _GEN, "contact_f1", ">=", 0.80),
)


def prompts(n: int) -> list[tuple[str, str]]:
    """Round-robin over intents, then over each intent's (object, hand mode) combinations."""
    combos = combinations()
    out, k = [], 0
    while len(out) < n and k < 1000:
        for intent, pairs in combos.items():
            if len(out) == n or not pairs:
                continue
            obj, mode = pairs[(k * 7) % len(pairs)]
            contact = mode_contact(mode)
            gender = ("female", "male")[len(out) % 2]
            out.append((describe(gender, intent, obj, contact, True)[1], f"{intent} {obj} {mode}"))
        k += 1
    return out


def held_out_wording(k: int, meaning: str) -> str:
    """A held-out wording (``grab.paraphrase.one(..., held_out=True)``) of the meaning
    ("intent object mode") of the k-th prompt of ``prompts`` (k from 0)."""
    intent, obj, mode = meaning.split()
    gender = ("female", "male")[k % 2]  # as prompts alternates
    return one(Meaning.of_mode(gender, intent, obj, mode), random.Random(f"held-out {k}"), held_out=True)


def _foot_sliding(npz: Path) -> float:
    """CHOIS foot sliding (``metrics.foot_sliding``) of an engine stream's FK joints, mm per frame."""
    import numpy as np

    from comgrasp_train.metrics import foot_sliding

    with np.load(npz) as f:
        return foot_sliding(f["joint_positions"].astype(np.float64), float(f["fps"]))


def bars(out: Path, earlier: Path | None = None) -> str:
    # No table.json: the engine-only report (quality_report.sh with ENGINE_ONLY=1), which
    # reads PyTorch's rows from the bundle's earlier table (its checkpoints are not here to
    # measure them again) and says where each such row comes from.
    source = ""
    if (out / "table.json").is_file():
        table = json.loads((out / "table.json").read_text())
    elif earlier is not None and earlier.is_file():
        table, source = json.loads(earlier.read_text()), f" (from {earlier})"
    else:
        table = {}
    lines = ["| bar | measured | target | met |", "|---|---|---|---|"]
    for label, prefixes, key, op, bound in BARS:
        found = next(((name, r) for prefix in prefixes for name, r in table.items()
                      if name.startswith(prefix) and key in r), None)
        if found is None:
            lines.append(f"| {label} | not measured | {op} {bound} | – |")
            continue
        name, row = found
        v = row[key]["mean"]
        met = v <= bound if op == "<=" else v >= bound
        stage = " (contact stage)" if "contact stage" in name else ""
        lines.append(f"| {label}{stage}{source} | {v:.3f} ± {row[key]['ci95']:.3f} | {op} {bound} | "
                     f"{'yes' if met else 'no'} |")
    # The contact stage's generation row where the table has one (its feet are planted), as
    # for the other generation bars.
    gen = next((r for prefix in ("generation, contact stage (", "generation (") for name, r in table.items()
                if name.startswith(prefix)), None)
    # SynthGrasp's ground truth slides ~0 (table.md: 0.000); the engine rows use the table's
    # where there is one.
    gt = gen["foot_sliding_gt_mm"]["mean"] if gen and "foot_sliding_gt_mm" in gen else 0.0
    if gen and "foot_sliding_mm" in gen:
        v = gen["foot_sliding_mm"]["mean"]
        bound = 1.5 * gt + 1.0
        lines.append(f"| generation foot sliding (mm/frame){source} | {v:.3f} | <= 1.5 x GT ({gt:.3f}) + 1 = {bound:.3f} | "
                     f"{'yes' if v <= bound else 'no'} |")
    for mode, what in (("stage", "engine frames"), ("raw", "engine frames, raw (no contact stage)")):
        files = sorted((out / "engine").glob(f"p*_s*_{mode}.npz"))
        if files:
            v = sum(map(_foot_sliding, files)) / len(files)
            bound = 1.5 * gt + 1.0
            lines.append(f"| {what}: foot sliding, mm/frame ({len(files)} samples) | {v:.3f} | "
                         f"<= 1.5 x GT ({gt:.3f}) + 1 = {bound:.3f} | {'yes' if v <= bound else 'no'} |")
    # The engine's own frames (what a host gets): the generation bars where the engine runs
    # through its contact stage, on the template prompts and on their held-out wordings.
    for name, what, targets in (
        ("engine.json", "engine frames, template prompts", {"intent_ok": 0.90, "intent_grasp": 0.95}),
        ("engine_held_out.json", "engine frames, held-out wordings", {"intent_ok": 0.80, "intent_grasp": 0.95}),
        ("engine_raw.json", "engine frames, raw (no contact stage)", {}),
    ):
        engine = out / name
        if engine.is_file():
            e = json.loads(engine.read_text())
            for k in ("intent_ok", "intent_grasp", "intent_unheld_still"):
                if k in e["rates"]:
                    v, bound = e["rates"][k], targets.get(k)
                    cells = "– | –" if bound is None else f">= {bound} | {'yes' if v >= bound else 'no'}"
                    lines.append(f"| {what}: {k} ({e['n']} samples) | {v:.3f} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) == 3 and argv[1] in ("prompts", "held-out"):
        for k, (text, meaning) in enumerate(prompts(int(argv[2]))):
            print(f"{text if argv[1] == 'prompts' else held_out_wording(k, meaning)}\t{meaning}")
        return 0
    if len(argv) in (3, 4) and argv[1] == "bars":
        text = bars(Path(argv[2]), Path(argv[3]) if len(argv) == 4 else None)
        (Path(argv[2]) / "bars.md").write_text(text)
        print(text)
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv))
