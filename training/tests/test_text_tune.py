"""Tuning the text encoder towards the meanings (train/text_tune.py) and carrying the tuned
encoder in a bundle (export/bundle.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from comgrasp_train.grab.paraphrase import Meaning
from comgrasp_train.synth.generate import combinations
from comgrasp_train.train.text_tune import (
    TUNED_FILE,
    TextTuneConfig,
    load_tuned,
    make_wordings,
    synthgrasp_meanings,
    tune_text_encoder,
)

SMALL = [Meaning(g, intent, obj, hands) for g in ("male", "female")
         for intent, obj, hands in (("lift", "mug", "left"), ("drink", "mug", "right"), ("pour", "wineglass", "left"),
                                    ("inspect", "apple", "right"))]


def test_the_wordings_cover_every_meaning_and_the_held_out_ones_are_unseen():
    meanings = synthgrasp_meanings()
    assert len(meanings) == 2 * sum(len(p) for p in combinations().values())
    assert len(set(meanings)) == len(meanings)
    w = make_wordings(meanings, TextTuneConfig(wordings=4, held_out=2))
    per = np.bincount([k for _, k in w.train], minlength=len(meanings))
    assert per.min() >= 8 + 1  # the 8 templates and at least one paraphrase
    assert np.bincount([k for _, k in w.held_out], minlength=len(meanings)).tolist() == [2] * len(meanings)
    train = {t for t, _ in w.train}
    assert not train & {t for t, _ in w.held_out}
    k = meanings.index(Meaning("female", "lift", "mug", "left"))
    assert w.train[w.canonical[k]] == ("The woman is lifting the mug with her left hand.", k)  # describe()[1]


def test_config_checks_and_round_trips():
    cfg = TextTuneConfig(steps=3, keep=0.25)
    assert TextTuneConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    for bad in ({"keep": 1.5}, {"weights": "int3"}, {"steps": 0}, {"lr": 0.0}, {"anchor": "mode"}):
        with pytest.raises(ValueError):
            TextTuneConfig(**bad)
    with pytest.raises(ValueError, match="unknown"):
        TextTuneConfig.from_dict({"stepz": 3})


def _tune(tmp_path, keep: float, steps: int = 30, anchor: str = "template"):
    """Tune MiniLM on the 8 meanings of SMALL."""
    from comgrasp_train.text_encoder import load_text_encoder

    cfg = TextTuneConfig(steps=steps, batch=16, lr=1e-4, warmup=5, keep=keep, anchor=anchor, wordings=6, held_out=3,
                         weights="fp32")
    student = load_text_encoder()
    rep = tune_text_encoder(cfg, load_text_encoder(), student, tmp_path, meanings=SMALL)
    return cfg, rep, student


def test_tuning_pulls_each_wording_to_its_meanings_centroid(tmp_path):
    """keep=0, anchor=centroid: the targets are the meanings' centroids, so after tuning the
    training wordings sit nearer theirs, and so do held-out wordings it never saw; the
    embedding tables do not move."""
    from comgrasp_train.text_encoder import load_text_encoder

    _, rep, student = _tune(tmp_path, keep=0.0, anchor="centroid")
    for part in ("train", "held_out"):
        b, a = rep["before"][part], rep["after"][part]
        assert a["cos"] > b["cos"] + 0.03, (part, b, a)
    assert rep["after"]["train"]["intent"] == 1.0
    fresh = load_text_encoder().network.state_dict()
    tuned = student.network.state_dict()
    for k in fresh:
        same = torch.equal(fresh[k], tuned[k])
        assert same == k.startswith("embeddings."), k
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 30
    assert json.loads((tmp_path / "config.json").read_text())["keep"] == 0.0
    # the saved state is what was trained, and loads back into a fresh encoder
    again = load_tuned(load_text_encoder(), tmp_path / TUNED_FILE)
    texts = ["The man lifts the mug with his left hand.", "drink from the mug"]
    assert torch.allclose(again.encode_uncached(texts), student.encode_uncached(texts), atol=1e-6)


def test_anchored_on_the_template_paraphrases_come_to_it_and_it_stays(tmp_path):
    """anchor=template: each meaning's wordings are pulled to its canonical template's frozen
    embedding (the form the Transformers saw most), held-out ones included, while that
    template's own embedding, its own target, stays where it was."""
    from comgrasp_train.text_encoder import load_text_encoder

    cfg, _, student = _tune(tmp_path, keep=0.0)
    frozen = load_text_encoder()
    w = make_wordings(SMALL, cfg)
    canon = frozen.encode_uncached([w.train[i][0] for i in w.canonical])
    para = [(t, k) for i, (t, k) in enumerate(w.train) if i not in set(w.canonical)]

    def to_anchor(enc, pairs):
        e = enc.encode_uncached([t for t, _ in pairs])
        return float((e * canon[torch.tensor([k for _, k in pairs])]).sum(1).mean())

    for pairs in (para, w.held_out):
        assert to_anchor(student, pairs) > to_anchor(frozen, pairs) + 0.03
    stay = (student.encode_uncached([w.train[i][0] for i in w.canonical]) * canon).sum(1)
    assert float(stay.min()) > 0.97, stay


def test_keep_one_leaves_the_encoder_where_it_was(tmp_path):
    """keep=1: every target is the wording's own frozen embedding, where the student starts
    (it moves only by what dropout's noise teaches it); keep=0 moves it much further."""
    from comgrasp_train.text_encoder import load_text_encoder

    texts = ["The woman is lifting the mug with her left hand.", "Drink from the mug using your right hand",
             "A guy inspects the apple right-handed."]
    frozen = load_text_encoder().encode_uncached(texts)
    moved = {}
    for keep in (1.0, 0.0):
        _, _, student = _tune(tmp_path / str(keep), keep=keep, steps=8)
        moved[keep] = float(1 - (student.encode_uncached(texts) * frozen).sum(1).min())
    assert moved[1.0] < 0.03 and moved[0.0] > 2 * moved[1.0], moved


def test_load_tuned_refuses_another_network(tmp_path):
    from comgrasp_train.export.tiny import tiny_text_encoder

    sd = {k: v for k, v in tiny_text_encoder(0).network.state_dict().items() if not k.startswith("embeddings.")}
    sd.pop(next(iter(sd)))
    torch.save(sd, tmp_path / "t.pt")
    with pytest.raises(ValueError, match="not a tuned state"):
        load_tuned(tiny_text_encoder(0), tmp_path / "t.pt")
