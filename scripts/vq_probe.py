"""Where a trained VQ loses the motion, in minutes instead of `evaluate`'s hour: held-out
sequences encoded and decoded whole, as `evaluate` and the engine decode them.

    .venv/bin/python scripts/vq_probe.py --data data/sg3000_prep runs/a runs/b

Per run (its best checkpoint), one JSON line:
* on ``--limit`` test sequences (the subjects in turn): FK joint error in mm from the features
  (``mpjpe``; ``global``, ``body``, ``hands``: only that component reconstructed, the rest
  ground truth, so each is charged its own error), the object's position error
  (``object_mm``) and the angle between each decoded hand frame and the true one
  (``hand_deg``, ``models.vq_losses.hand_axes``: the turn a held object takes from the hand),
  the signed height error of the resting object (``rest_up_mm``, frame 0) and how far above
  its resting object each grasping wrist closes (``grasp_up_mm``; ``grasp_up_gt_mm`` the
  same for the ground truth; ``intent_check.grasp_offsets``);
* on every test sequence of each ``--intent`` (default pour; a comma list, or ``all`` for
  SynthGrasp's six): the reconstruction through the engine's contact stage against its
  prompt, as `evaluate` checks it: ``intent_ok`` (``obeyed`` of ``sequences``) and the
  intent's own rule (``rule_ok``; the share of all sequences), and the median of the rule's
  value (pour: the largest tilt of the held object) over the sequences that grasp at all;
  with more than one intent also ``pooled``, ``intent_ok`` over all their sequences.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from comgrasp_train.evaluate import outputs_of, prompt_for, reconstruct
from comgrasp_train.intent_check import SYNTH_INTENTS, check_features, grasp_offsets, intent_of, track_from_features
from comgrasp_train.layout import COMPONENT_SLICES, FIELD
from comgrasp_train.metrics import rotation_angle_deg
from comgrasp_train.models.vq_losses import hand_axes
from comgrasp_train.normalization import Normalizer
from comgrasp_train.representation import features_to_joints
from comgrasp_train.train.vq_trainer import load_prepared, load_vq

RULE_VALUE = {"pour": "tilt_deg", "lift": "rise_m", "drink": "head_m", "inspect": "turn_deg", "offhand": "reach_frac"}


def fk_rows(vq, norm, fs) -> dict[str, float]:
    rows = {k: [] for k in ("mpjpe", "global", "body", "hands", "object_mm", "hand_deg", "rest_up_mm")}
    grasp = {"grasp_up_mm": [], "grasp_up_gt_mm": []}
    for gt, rest in zip(fs.features, fs.rest_joints):
        rest = torch.from_numpy(np.asarray(rest)).float()
        rec = reconstruct(vq, norm, gt)
        true = features_to_joints(torch.from_numpy(gt), rest)

        def err(x):
            return float((features_to_joints(torch.from_numpy(x), rest) - true).norm(dim=-1).mean() * 1000)

        rows["mpjpe"].append(err(rec))
        for name, parts in (("global", ("global",)), ("body", ("body",)), ("hands", ("lhand", "rhand"))):
            h = gt.copy()
            for p in parts:
                h[:, COMPONENT_SLICES[p]] = rec[:, COMPONENT_SLICES[p]]
            rows[name].append(err(h))
        s = FIELD["object_transl"].slice
        rows["object_mm"].append(float(np.linalg.norm(rec[:, s] - gt[:, s], axis=-1).mean() * 1000))
        a, b = hand_axes(features_to_joints(torch.from_numpy(rec), rest)), hand_axes(true)
        rows["hand_deg"].append(float(rotation_angle_deg(a.numpy(), b.numpy()).mean()))
        rows["rest_up_mm"].append(float(rec[0, s][2] - gt[0, s][2]) * 1000)
        for key, x in (("grasp_up_mm", rec), ("grasp_up_gt_mm", gt)):
            grasp[key] += (grasp_offsets(track_from_features(x, rest, fs.fps))[:, 2] * 1000).tolist()
    return {k: round(float(np.mean(v)), 1) for k, v in {**rows, **grasp}.items()}


def intent_rows(vq, norm, fs, intent: str) -> dict[str, float]:
    ok, rule, values = [], [], []
    for i, m in enumerate(fs.meta):
        if m.get("intent") != intent:
            continue
        rec = reconstruct(vq, norm, fs.features[i])
        staged = outputs_of(rec, m, fs.rest_joints[i], fs.fps, ("stage",))["stage"]
        r = check_features(staged, prompt_for(fs, i), m, fs.rest_joints[i], fs.fps, intent=intent_of(m))
        ok.append(r.ok)
        rule.append(r.rules.get(intent, False))
        if RULE_VALUE.get(intent) in r.values:
            values.append(r.values[RULE_VALUE[intent]])
    if not ok:
        raise SystemExit(f"no test sequence has intent {intent!r}")
    return {"sequences": len(ok), "obeyed": int(sum(ok)), "intent_ok": round(float(np.mean(ok)), 3), "rule_ok": round(float(np.mean(rule)), 3),
            f"median_{RULE_VALUE.get(intent, 'value')}": round(float(np.median(values)), 3) if values else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="train-vq output folders")
    ap.add_argument("--data", required=True, help="a prepared SynthGrasp folder (its test part)")
    ap.add_argument("--limit", type=int, default=60, help="test sequences for the FK errors")
    ap.add_argument("--intent", default="pour",
                    help="SynthGrasp intents checked through the contact stage (comma list, or all)")
    args = ap.parse_args(argv)
    torch.set_grad_enabled(False)
    fs = load_prepared(args.data, "test")[0]
    intents = SYNTH_INTENTS if args.intent == "all" else args.intent.split(",")
    for run in args.runs:
        vq, _, info = load_vq(run, which="best")
        norm = Normalizer.load(Path(run) / "stats.npz")  # the run's own, as evaluate reads it
        out = {"run": run, "step": info["checkpoint"]["step"], **fk_rows(vq, norm, fs.spread(args.limit))}
        for intent in intents:
            out[intent] = intent_rows(vq, norm, fs, intent)
        if len(intents) > 1:  # pooled over the sequences, not averaged over the intents
            n = sum(out[i]["sequences"] for i in intents)
            out["pooled"] = {"sequences": n, "intent_ok": round(sum(out[i]["obeyed"] for i in intents) / n, 3)}
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
