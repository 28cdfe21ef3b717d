"""Evaluation on a test split: VQ reconstruction and text-to-motion generation, with the
paper's metric suite, written as a Table I-like report (Markdown + JSON).

Reconstruction: every test sequence through encode -> decode. Generation: each test
sequence's first description, ``repeats`` times with different seeds; prediction and
ground truth are compared over their common length (generated lengths differ).
Besides Table I, reconstruction reports hand contact accuracy (decoded contact
probability > 0.5 vs the labels, over frames x hands), and both the share of motions that
obey their prompt (``intent_ok``, the whole motion through ``intent_check``; per-rule rates
``intent_<rule>`` in the JSON), with the ground truth's for reference. Reconstruction's is
the ceiling of generation's through this VQ: a pour the VQ decodes with 15 deg of tilt
fails the checker whatever the Transformer samples.

Both run the motion as the model makes it (``raw``) and, with ``outputs`` naming it, through
the engine's contact-consistency stage (``stage``: ``contact_stage``, the same frames the
engine streams by default), measured on the same samples side by side.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .body_model import BodyModelConfig, make_body_model
from .contact_stage import ObjectShape, apply_contact_stage
from .dataset import FeatureSet
from .grab.paraphrase import Meaning, paraphrases
from .intent_check import check_feature_set, check_features, intent_of
from .metrics import METRIC_KEYS, MetricConfig, compute_metrics, sample_from_pose, summarize, summarize_repeats
from .models.sampling import SamplingParams
from .models.vqvae import fit_to_tokens
from .normalization import Normalizer
from .objects.sdf import load_object_sdf
from .representation import features_to_params


def _sample(x: np.ndarray, meta: dict, rest: np.ndarray, body, fps: float):
    p = features_to_params(x, torch.from_numpy(rest).double())
    subject = body.subject_from_rest(rest, meta.get("gender", "neutral")) if body.backend == "open" \
        else body.subject(meta["gender"], meta.get("vtemp"))
    return sample_from_pose(body, subject, torch.from_numpy(p["rotmats"]), torch.from_numpy(p["transl"]),
                            p["object_rotmat"], p["object_transl"], load_object_sdf(meta["object_mesh"]), fps,
                            contact=p["contact"], name=meta.get("name", ""))


def _pair_metrics(pred: np.ndarray, gt: np.ndarray, meta: dict, rest: np.ndarray, body, fps, cfg) -> dict:
    T = min(len(pred), len(gt))
    return compute_metrics(_sample(pred[:T], meta, rest, body, fps), _sample(gt[:T], meta, rest, body, fps), cfg)


OUTPUTS = ("raw", "stage")


def outputs_of(pred: np.ndarray, meta: dict, rest: np.ndarray, fps: float, outputs=("raw",)) -> dict[str, np.ndarray]:
    """A de-normalized motion as each of ``outputs`` shows it: ``raw`` (the model's) and/or
    ``stage`` (through the engine's contact-consistency stage, the whole motion streamed)."""
    if unknown := set(outputs) - set(OUTPUTS):
        raise ValueError(f"outputs must be among {OUTPUTS}, got {sorted(unknown)}")
    out = {}
    for o in outputs:
        out[o] = pred if o == "raw" else apply_contact_stage(pred, rest, fps, ObjectShape.for_meta(meta))
    return out


@torch.no_grad()
def reconstruct(vq, norm: Normalizer, gt: np.ndarray, device: torch.device | str = "cpu") -> np.ndarray:
    """One de-normalized sequence (T, 335) encoded and decoded whole, as the engine decodes it."""
    x = fit_to_tokens(torch.from_numpy(norm.normalize(gt.astype(np.float32)))[None].to(device), vq.frames_per_token, "pad")
    return norm.denormalize(vq.decode(vq.encode(x))[0].cpu().numpy())[: len(gt)]


@torch.no_grad()
def evaluate_reconstruction(vq, norm: Normalizer, fs: FeatureSet, body=None, cfg=MetricConfig(),
                            limit: int | None = None, outputs=("raw",)) -> dict[str, list[dict]]:
    """Runs on the model's own device (the inputs follow the weights). Rows per output."""
    body = body or make_body_model(BodyModelConfig())
    device = next(vq.parameters()).device
    rows = {o: [] for o in outputs}
    for i, gt in enumerate(fs.features[:limit]):
        rec = reconstruct(vq, norm, gt, device)
        for o, pred in outputs_of(rec, fs.meta[i], fs.rest_joints[i], fs.fps, outputs).items():
            row = _pair_metrics(pred, gt, fs.meta[i], fs.rest_joints[i], body, fs.fps, cfg)
            row["contact_accuracy"] = float(((pred[:, [240, 334]] > 0.5) == (gt[:, [240, 334]] > 0.5)).mean())
            row.update(check_features(pred, prompt_for(fs, i), fs.meta[i], fs.rest_joints[i], fs.fps,
                                      intent=intent_of(fs.meta[i])).row())
            rows[o].append(row)
    return rows


PROMPTS = ("template", "held_out")


def prompt_for(fs: FeatureSet, i: int, prompts: str = "template") -> str:
    """The prompt a test sequence is generated from: its canonical template text, or one
    wording of ``grab.paraphrase``'s held-out set (phrasings no training text uses)."""
    if prompts == "template":
        return fs.texts[i][0]
    if prompts == "held_out":
        return paraphrases(Meaning.of(fs.meta[i]), 1, fs.meta[i].get("name", i), held_out=True)[0]
    raise ValueError(f"prompts must be one of {PROMPTS}, got {prompts!r}")


def evaluate_generation(model, fs: FeatureSet, repeats: int = 3, params: SamplingParams = SamplingParams(),
                        seed: int = 0, body=None, cfg=MetricConfig(), limit: int | None = None,
                        batch: int = 32, prompts: str = "template", outputs=("raw",)) -> dict[str, list[list[dict]]]:
    """Generation from each test sequence's prompt (``prompt_for``), ``repeats`` seeds; the
    prompt checks read the sequence's own intent, hand(s) and object (``intent_of``). Rows
    per output (the same samples), then per repeat."""
    body = body or make_body_model(BodyModelConfig())
    n = len(fs.features[:limit])
    texts = [prompt_for(fs, i, prompts) for i in range(n)]
    out = {o: [] for o in outputs}
    for r in range(repeats):
        rows = {o: [] for o in outputs}
        for a in range(0, n, batch):
            idx = range(a, min(n, a + batch))
            preds = model.generate([texts[i] for i in idx], params, seed=seed + 100_003 * r + a)
            for p, i in zip(preds, idx):
                meta, rest = fs.meta[i], fs.rest_joints[i]
                for o, pred in outputs_of(p, meta, rest, fs.fps, outputs).items():
                    rows[o].append({**_pair_metrics(pred, fs.features[i], meta, rest, body, fs.fps, cfg),
                                    **check_features(pred, texts[i], meta, rest, fs.fps, intent=intent_of(meta)).row()})
        for o in outputs:
            out[o].append(rows[o])
    return out


def evaluate_ground_truth_intent(fs: FeatureSet, limit: int | None = None) -> list[dict]:
    """The prompt checks of the test sequences themselves (the reference for generation's)."""
    return [r.row() for r in check_feature_set(fs, limit)]


def write_report(results: dict[str, dict], path_md: Path,
                 extra_keys=("contact_accuracy", "intent_ok", "intent_grasp", "foot_sliding_gt_mm")) -> None:
    """results: setting -> {key: Summary}. Writes Markdown and the JSON beside it."""
    keys = list(METRIC_KEYS) + [k for k in extra_keys if any(k in r for r in results.values())]
    lines = ["| setting | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name, summ in results.items():
        cells = [f"{summ[k].mean:.3f} ± {summ[k].ci95:.3f}" if k in summ else "–" for k in keys]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    path_md = Path(path_md)
    path_md.parent.mkdir(parents=True, exist_ok=True)
    path_md.write_text("\n".join(lines) + "\n\nmean ± 95% interval (1.96·sd/√n); mm unless stated.\n")
    path_md.with_suffix(".json").write_text(json.dumps(
        {name: {k: {"mean": v.mean, "ci95": v.ci95, "n": v.n} for k, v in s.items()} for name, s in results.items()},
        indent=1))


__all__ = ["OUTPUTS", "outputs_of", "evaluate_reconstruction", "evaluate_generation", "evaluate_ground_truth_intent",
           "write_report", "summarize", "summarize_repeats"]
