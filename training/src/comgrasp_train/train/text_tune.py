"""Tune the text encoder so that wordings the Transformers never saw land where their
meaning's training wordings do.

The Transformers are conditioned on a frozen sentence embedding (all-MiniLM-L6-v2), and
that embedding separates what a prompt means poorly for unseen phrasings: on SynthGrasp's
held-out wordings (``grab.paraphrase``'s ``HELD_OUT`` verbs, subjects and hand phrases),
the training meaning whose centroid is nearest has the right hand mode in ~63 % of cases
and the right intent in ~72 %. A retrain of the Transformers on another text path is hours;
this leaves them as they are and moves the encoder instead:

* the meanings are every SynthGrasp (intent, object, hand mode) and gender;
* their training wordings are the paper's templates plus ``wordings`` training-grammar
  paraphrases each, never a held-out one;
* the target of a wording is ``normalize(keep * frozen(w) + (1 - keep) * anchor(m))``,
  where a meaning's anchor is the frozen embedding of its canonical template
  (``describe()[1]``, "The woman is lifting the mug with her left hand.": the paper's form,
  in every training sequence of that meaning, and the template prompt of the quality
  report) or, with ``anchor="centroid"``, the mean of the frozen embeddings of all its
  training wordings. At keep = 0 every wording of a meaning is taught to read as its
  template, which the Transformers follow best; the template itself keeps its own
  embedding, its target;
* the student is the same MiniLM, its embedding tables frozen (rows of words absent from the
  training grammar, e.g. the held-out verbs, keep what pretraining gave them), trained on
  ``1 - cos(student(w), target(w))``.

``frozen`` is the encoder rounded as the Transformers were trained with (``weights``); the
student is trained in fp32 and rounded the same way when it is exported. The report holds
the nearest-centroid accuracy of every factor (intent, object, hand mode, gender) on the
training and the held-out wordings, before and after. The bundle records the config and
the report (``provenance.text_encoder_weights.tuned``) and holds the tuned weights in
``native/text/``, from which ``export.bundle.bundle_text_encoder`` rebuilds it.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..export.text_encoder_export import sha256_file
from ..grab.paraphrase import Meaning, mode_contact, paraphrases
from ..grab.text import describe
from ..text_encoder import TEXT_WEIGHTS, TextEncoder, pool_token_states

TUNED_FILE = "text_tuned.pt"
CONFIG_FILE = "config.json"
REPORT_FILE = "report.json"
FACTORS = ("intent", "object", "hands", "gender")
ANCHORS = ("template", "centroid")
CANONICAL = 1  # describe()'s "The {person} is {ing} ..." form, the quality report's template prompt


@dataclass(frozen=True)
class TextTuneConfig:
    steps: int = 400
    batch: int = 64
    lr: float = 5e-5
    warmup: int = 50
    weight_decay: float = 0.01
    keep: float = 0.0  # weight of the wording's own frozen embedding in its target (the rest: its meaning's anchor)
    anchor: str = "template"  # a meaning's anchor: its canonical template's frozen embedding, or "centroid"
    wordings: int = 32  # training-grammar paraphrases per meaning, beyond the paper's templates
    held_out: int = 8  # held-out wordings per meaning, for the report only (never trained on)
    weights: str = "int8-tok4"  # the text weights the Transformers were trained with: targets and export
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.keep <= 1.0:
            raise ValueError(f"keep must be in [0, 1], got {self.keep}")
        if self.anchor not in ANCHORS:
            raise ValueError(f"anchor must be one of {ANCHORS}, got {self.anchor!r}")
        if self.weights not in TEXT_WEIGHTS:
            raise ValueError(f"weights must be one of {TEXT_WEIGHTS}, got {self.weights!r}")
        if min(self.steps, self.batch, self.wordings) < 1 or self.held_out < 0 or self.lr <= 0:
            raise ValueError("steps, batch and wordings must be >= 1, held_out >= 0 and lr > 0")

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> TextTuneConfig:
        known = {f.name for f in fields(TextTuneConfig)}
        if set(d) - known:
            raise ValueError(f"unknown TextTuneConfig fields: {sorted(set(d) - known)}")
        return TextTuneConfig(**d)


@dataclass(frozen=True)
class Wordings:
    meanings: list[Meaning]
    train: list[tuple[str, int]]  # (text, meaning index)
    held_out: list[tuple[str, int]]
    canonical: list[int]  # per meaning, the index in train of its canonical template


def synthgrasp_meanings() -> list[Meaning]:
    """Every SynthGrasp (intent, object, hand mode), for each gender."""
    from ..synth.generate import combinations

    return [Meaning.of_mode(g, intent, obj, mode) for intent, pairs in combinations().items()
            for obj, mode in pairs for g in ("male", "female")]


def make_wordings(meanings: list[Meaning], cfg: TextTuneConfig) -> Wordings:
    """The training wordings of each meaning (templates, then ``cfg.wordings`` paraphrases)
    and ``cfg.held_out`` held-out ones, seeded per meaning."""
    train, held, canonical = [], [], []
    for k, m in enumerate(meanings):
        texts = describe(m.gender, m.intent, m.obj_name, mode_contact(m.mode), True)
        canonical.append(len(train) + CANONICAL)
        texts += paraphrases(m, cfg.wordings, f"tune {cfg.seed} {k}")
        train += [(t, k) for t in dict.fromkeys(texts)]
        held += [(t, k) for t in paraphrases(m, cfg.held_out, f"tune held-out {cfg.seed} {k}", held_out=True)]
    return Wordings(meanings, train, held, canonical)


def centroids(emb: torch.Tensor, labels: torch.Tensor, k: int) -> torch.Tensor:
    """(k, dim) unit mean embedding of each meaning."""
    c = torch.zeros(k, emb.shape[1], dtype=emb.dtype).index_add_(0, labels, emb)
    return F.normalize(c, dim=1)


def factor_accuracy(emb: torch.Tensor, labels: list[int], cents: torch.Tensor, meanings: list[Meaning]) -> dict:
    """How often the nearest centroid's meaning has the wording's intent, object, hand mode
    and gender, and the mean cosine to the wording's own centroid. Some misses are the
    grammar's: "Someone" has no gender, "the ball" names three spheres."""
    pred = (emb @ cents.T).argmax(1).tolist()

    def key(i: int) -> tuple:
        m = meanings[i]
        return m.intent, m.obj_name, m.mode, m.gender

    out = {f: float(np.mean([key(p)[j] == key(t)[j] for p, t in zip(pred, labels)])) for j, f in enumerate(FACTORS)}
    out["cos"] = float((emb * cents[torch.tensor(labels)]).sum(1).mean())
    return {k: round(v, 4) for k, v in out.items()}


def _embedding_params(name: str) -> bool:
    return name.startswith("embeddings.")


def tuned_state(student: TextEncoder) -> dict[str, torch.Tensor]:
    """The parameters tuning changes (everything but the embedding tables)."""
    return {k: v.detach().clone() for k, v in student.network.state_dict().items() if not _embedding_params(k)}


def load_tuned(encoder: TextEncoder, path: str | Path) -> TextEncoder:
    """Put the tuned parameters of ``path`` (``TUNED_FILE``) into a fp32 MiniLM ``encoder``."""
    if encoder.weights != "fp32":
        raise ValueError("load the tuned weights before rounding the text encoder")
    sd = torch.load(Path(path), map_location="cpu", weights_only=True)
    own = encoder.network.state_dict()
    bad = [k for k in sd if k not in own or own[k].shape != sd[k].shape]
    if bad or set(own) - set(sd) - {k for k in own if _embedding_params(k)}:
        raise ValueError(f"{path}: not a tuned state of this text encoder (e.g. {(bad or sorted(set(own) - set(sd)))[:3]})")
    encoder.network.load_state_dict(sd, strict=False)
    encoder.clear_cache()
    return encoder


def tune_text_encoder(cfg: TextTuneConfig, frozen: TextEncoder, student: TextEncoder, out_dir: str | Path,
                      meanings: list[Meaning] | None = None, progress: bool = False) -> dict:
    """Train ``student`` (fp32, the same network as ``frozen``) in place; writes
    ``out_dir``/``TUNED_FILE``, ``CONFIG_FILE``, ``REPORT_FILE`` and ``log.jsonl``; returns
    the report. ``frozen``: rounded as ``cfg.weights``; ``meanings``: default
    :func:`synthgrasp_meanings`."""
    if frozen.weights != cfg.weights or student.weights != "fp32":
        raise ValueError(f"frozen must be rounded as {cfg.weights!r} and the student fp32 "
                         f"(got {frozen.weights!r}, {student.weights!r})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / CONFIG_FILE).write_text(json.dumps(cfg.to_dict(), indent=1) + "\n", encoding="utf-8")
    t0 = time.time()
    words = make_wordings(meanings if meanings is not None else synthgrasp_meanings(), cfg)
    k = len(words.meanings)
    texts, labels = [t for t, _ in words.train], [i for _, i in words.train]
    y = torch.tensor(labels)
    emb = frozen.encode_uncached(texts)
    cents = centroids(emb, y, k)
    anchors = emb[torch.tensor(words.canonical)] if cfg.anchor == "template" else cents
    targets = F.normalize(cfg.keep * emb + (1 - cfg.keep) * anchors[y], dim=1)

    def report(enc: TextEncoder) -> dict:
        r = {"train": factor_accuracy(emb if enc is frozen else enc.encode_uncached(texts), labels, cents,
                                      words.meanings)}
        if words.held_out:
            r["held_out"] = factor_accuracy(enc.encode_uncached([t for t, _ in words.held_out]),
                                            [i for _, i in words.held_out], cents, words.meanings)
        return r

    before = report(frozen)
    torch.manual_seed(cfg.seed)
    net = student.network
    for name, p in net.named_parameters():
        p.requires_grad_(not _embedding_params(name))
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: (s + 1) / cfg.warmup if s < cfg.warmup else max(0.0, 1 - s / cfg.steps) ** 0.5)
    inputs = {n: torch.from_numpy(a) for n, a in student.tokenize(texts).items()}
    gen = torch.Generator().manual_seed(cfg.seed)
    with (out / "log.jsonl").open("w", encoding="utf-8") as log:
        for step in range(1, cfg.steps + 1):
            idx = torch.randint(0, len(texts), (cfg.batch,), generator=gen)
            net.train()
            states = net(*[inputs[n][idx] for n in student.input_names])
            states = states[0] if isinstance(states, (tuple, list)) else states
            e = pool_token_states(states, inputs["input_ids"][idx], inputs["attention_mask"][idx],
                                  pooling=student.pooling, normalize=student.normalize)
            loss = (1 - (e * targets[idx]).sum(1)).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if step % 50 == 0 or step == cfg.steps:
                rec = {"step": step, "loss": round(loss.item(), 5), "seconds": round(time.time() - t0, 1)}
                log.write(json.dumps(rec) + "\n")
                log.flush()
                if progress:
                    print(rec, flush=True)
    net.eval()
    for p in net.parameters():
        p.requires_grad_(False)
    student.clear_cache()
    torch.save(tuned_state(student), out / TUNED_FILE)
    rounded = _rounded_copy(student, cfg.weights)
    rep = {"meanings": k, "train_wordings": len(texts), "held_out_wordings": len(words.held_out),
           "before": before, "after": report(rounded), "seconds": round(time.time() - t0, 1),
           "sha256": sha256_file(out / TUNED_FILE)}
    (out / REPORT_FILE).write_text(json.dumps(rep, indent=1) + "\n", encoding="utf-8")
    return rep


def _rounded_copy(student: TextEncoder, weights: str) -> TextEncoder:
    """The student rounded as the bundle will hold it (the student itself stays fp32)."""
    import copy

    from ..text_encoder import apply_text_weights

    enc = copy.deepcopy(student)
    return apply_text_weights(enc, weights)


__all__ = ["CONFIG_FILE", "REPORT_FILE", "TUNED_FILE", "TextTuneConfig", "Wordings", "centroids", "factor_accuracy", "load_tuned",
           "make_wordings", "synthgrasp_meanings", "tune_text_encoder", "tuned_state"]
