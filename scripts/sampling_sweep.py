"""How the sampler's temperature, top-k and classifier-free guidance change what a bundle's
motions do, on the engine's own frames.

    python scripts/sampling_sweep.py --bundle models/default --configs 1.0:0,0.8:0,0.6:10,1.0:0:2 \
        --prompts 24 --seeds 1,2,3,4 --out out/sweep

For every ``T:K`` or ``T:K:G`` config (G: the guidance scale, default the bundle's), every prompt of ``quality_report.py prompts N`` (every SynthGrasp
intent and hand mode) and its held-out wording (``grab.paraphrase.one(..., held_out=True)``:
verbs, subjects and hand phrases the training texts never use), and every seed, it runs
``comgrasp generate --fk`` (the default output, contact stage on) and checks the frames with
the quality report's checker against the prompt's meaning. Writes OUT/sweep.json (every
sample) and OUT/sweep.md (rates per config and prompt set, plus how often two seeds of the
same prompt give the same motion, so that a low temperature's loss of variety shows).

``--raw`` checks the model's raw frames instead (``generate --raw``). Every sample also
records its grasp offsets (``intent_check.grasp_offsets``: each grasping hand's wrist when
its flag comes on, minus the object's resting origin); the table shows their mean upward
part and mean length, and ``--reference DATA`` adds the same for a prepared set's test
motions. On raw frames that is where the model closes its hand against where it put the
object, which the contact stage has to make up.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from comgrasp_train.grab.text_parse import Intent, parse_prompt
from comgrasp_train.intent_check import check_motion, grasp_offsets, object_sdf_for, track_from_engine, track_from_features
from quality_report import held_out_wording, prompts

RATES = ("intent_ok", "intent_grasp", "intent_unheld_still", "intent_lift", "intent_drink", "intent_pour",
         "intent_pass", "intent_inspect", "intent_offhand")


def run_one(binary: str, bundle: str, text: str, seed: int, t: float, k: int, g: float | None, out: Path,
            intent: Intent, raw: bool = False) -> dict:
    if not out.exists():
        subprocess.run([binary, "generate", "--bundle", bundle, "--text", text, "--seed", str(seed), "--fk",
                        "--temperature", str(t), "--top-k", str(k), *(["--guidance", str(g)] if g is not None else []),
                        *(["--raw"] if raw else []), "--out", str(out)],
                       check=True, stdout=subprocess.DEVNULL)
    with np.load(out) as frames:
        frames = dict(frames)
    track = track_from_engine(frames, object_sdf_for({"object": intent.object}))
    r = check_motion(track, intent)
    return {"ok": r.ok, "reason": r.reason, **r.row(), "frames": len(frames["object_translation"]),
            "object_path": frames["object_translation"][::8].round(3).tolist(),
            "grasp_offsets": grasp_offsets(track).round(3).tolist()}


def offset_cells(offsets: list) -> str:
    """Table cells: mean up offset and mean length of grasp offsets, in cm."""
    o = np.array(offsets, float).reshape(-1, 3)
    return f"{100 * o[:, 2].mean():.1f} | {100 * np.linalg.norm(o, axis=1).mean():.1f}" if len(o) else "– | –"


def reference_offsets(data: str) -> list:
    """The ground truth's grasp offsets: every sequence of a prepared set's test part."""
    from comgrasp_train.dataset import FeatureSet

    fs = FeatureSet.load(Path(data) / "features_test.npz")
    return [o for x, rest in zip(fs.features, fs.rest_joints)
            for o in grasp_offsets(track_from_features(x, rest, fs.fps)).tolist()]


def parse_config(c: str) -> tuple[float, int, float | None]:
    """``T:K`` or ``T:K:G`` -> (temperature, top-k, guidance or None for the bundle's)."""
    parts = c.split(":")
    if len(parts) not in (2, 3):
        raise SystemExit(f"--configs: {c!r} is not TEMPERATURE:TOP_K[:GUIDANCE]")
    return float(parts[0]), int(parts[1]), float(parts[2]) if len(parts) == 3 else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", default="models/default")
    ap.add_argument("--binary", default="target/release/comgrasp")
    ap.add_argument("--configs", default="1.0:0,0.8:0,0.6:0,0.8:20,0.6:10,0.4:5",
                    help="comma-separated TEMPERATURE:TOP_K[:GUIDANCE]")
    ap.add_argument("--prompts", type=int, default=24)
    ap.add_argument("--seeds", default="1,2,3,4")
    ap.add_argument("--sets", default="template,held_out")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default="out/sweep")
    ap.add_argument("--raw", action="store_true", help="check the model's raw frames (generate --raw)")
    ap.add_argument("--reference", metavar="DATA",
                    help="a prepared SynthGrasp folder: add its test motions' grasp offsets as a row")
    a = ap.parse_args(argv)
    out = Path(a.out)
    (out / "npz").mkdir(parents=True, exist_ok=True)
    configs = [parse_config(c) for c in a.configs.split(",")]
    seeds = [int(s) for s in a.seeds.split(",")]
    cases = []  # (set, prompt index, text, intent)
    for k, (text, meaning) in enumerate(prompts(a.prompts)):
        intent_name, obj, mode = meaning.split()
        intent = Intent(intent_name, mode, obj)
        parsed = parse_prompt(text)
        if (parsed.intent, parsed.hands, parsed.object) != (intent.intent, intent.hands, intent.object):
            raise SystemExit(f"the checker reads {text!r} as {parsed}, not {intent}")
        for s in a.sets.split(","):
            cases.append((s, k, text if s == "template" else held_out_wording(k, meaning), intent))
    jobs = [(c, t, k, g, seed) for (t, k, g) in configs for c in cases for seed in seeds]

    def work(job):
        (s, i, text, intent), t, k, g, seed = job
        f = out / "npz" / f"t{t}_k{k}{'' if g is None else f'_g{g}'}{'_raw' if a.raw else ''}_{s}_p{i}_s{seed}.npz"
        row = run_one(a.binary, a.bundle, text, seed, t, k, g, f, intent, a.raw)
        return {"temperature": t, "top_k": k, "guidance": g, "set": s, "prompt": i, "text": text, "seed": seed, **row}

    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(work, jobs))
    (out / "sweep.json").write_text(json.dumps(rows, indent=0))
    lines = ["| T | top-k | guidance | prompts | n | " + " | ".join(r.removeprefix("intent_") for r in RATES)
             + " | same motion across seeds | frames | grasp offset up (cm) | grasp offset (cm) |",
             "|---" * (len(RATES) + 9) + "|"]
    for t, k, g in configs:
        for s in a.sets.split(","):
            sel = [r for r in rows if (r["temperature"], r["top_k"], r["guidance"]) == (t, k, g) and r["set"] == s]
            rates = [np.mean([r[x] for r in sel if x in r]) if any(x in r for r in sel) else float("nan")
                     for x in RATES]
            same = []  # pairs of seeds of one prompt whose object paths agree to 1 cm
            for i in {r["prompt"] for r in sel}:
                paths = [np.array(r["object_path"]) for r in sel if r["prompt"] == i]
                same += [p.shape == q.shape and float(np.abs(p - q).max()) < 0.01
                         for n, p in enumerate(paths) for q in paths[n + 1:]]
            lines.append(f"| {t} | {k} | {'bundle' if g is None else g} | {s} | {len(sel)} | " + " | ".join(f"{v:.2f}" for v in rates)
                         + f" | {np.mean(same):.2f} | {np.mean([r['frames'] for r in sel]):.0f} | "
                         + offset_cells([o for r in sel for o in r["grasp_offsets"]]) + " |")
    if a.reference:
        lines.append("| ground truth | | | test motions | | " + "| " * (len(RATES) + 2)
                     + offset_cells(reference_offsets(a.reference)) + " |")
    table = "\n".join(lines) + "\n"
    (out / "sweep.md").write_text(table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
