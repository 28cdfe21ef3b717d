"""Training wordings and the held-out wordings of grab.paraphrase, and prepare's workers."""

from __future__ import annotations

import numpy as np

from comgrasp_train.dataset import prepare_features
from comgrasp_train.grab import paraphrase as pp
from comgrasp_train.grab.splits import get_split
from comgrasp_train.intent_check import intent_of
from comgrasp_train.objects.catalogue import CATALOGUE

LEFT_DRINK = pp.Meaning("female", "drink", "mug", "left", "left", "left")
PASS = pp.Meaning("male", "pass", "spheremedium", "both", "right", "left")


def test_paraphrases_are_seeded_distinct_and_name_the_hand_and_object():
    a = pp.paraphrases(LEFT_DRINK, 12, "seq_7")
    assert a == pp.paraphrases(LEFT_DRINK, 12, "seq_7") and a != pp.paraphrases(LEFT_DRINK, 12, "seq_8")
    assert len(set(a)) == 12
    aliases = CATALOGUE["mug"].aliases
    for t in a:
        low = t.lower()
        assert "left" in low and "right" not in low, t
        assert any(x in low for x in aliases), t
    # a pass names the giver before the taker
    for t in pp.paraphrases(PASS, 10, 1) + pp.paraphrases(PASS, 4, 1, held_out=True):
        low = t.lower()
        assert low.index("right") < low.index("left"), t


def test_training_wordings_vary_form_and_case():
    texts = pp.paraphrases(pp.Meaning("male", "lift", "cubelarge", "right", "right", "right"), 40, 0)
    assert any(t[0].islower() for t in texts) and any(not t.endswith(".") for t in texts)
    assert any(t.lower().startswith(("lift", "pick", "raise", "grab")) for t in texts)  # imperatives
    assert any(" is " in t.lower() for t in texts)  # progressive


def test_held_out_wordings_never_appear_in_training_texts():
    train_words = pp._all_training_words()
    for intent, verbs in pp.HELD_OUT_VERBS.items():
        for v in verbs:
            assert not set(v) & train_words, v
            # no held-out verb phrase is a training phrase with another object
            assert all(f.split("{obj}")[0].strip() not in {t.split("{obj}")[0].strip() for tv in pp.TRAIN_VERBS[intent]
                                                             for t in tv if t} for f in v if f), v
    for seed in range(20):
        for m in (LEFT_DRINK, PASS):
            held = pp.paraphrases(m, 3, seed, held_out=True)
            train = pp.paraphrases(m, 200, seed)
            assert not set(held) & set(train)


def test_grab_intents_without_synonyms_keep_the_papers_phrase():
    texts = pp.paraphrases(pp.Meaning("male", "takepicture", "camera"), 6, 0)
    assert texts and all("picture" in t.lower() for t in texts)


def test_prepare_workers_give_the_same_result_and_paraphrases(grab_root):
    split = get_split("diffgrasp")
    one, s1 = prepare_features(grab_root, split, "train", mention_hands=True, workers=1, paraphrases=5)
    two, s2 = prepare_features(grab_root, split, "train", mention_hands=True, workers=2, paraphrases=5)
    assert s1.loaded == s2.loaded == len(one) > 0
    for a, b in zip(one.features, two.features):
        np.testing.assert_array_equal(a, b)
    assert one.texts == two.texts and one.meta == two.meta
    plain, _ = prepare_features(grab_root, split, "train", mention_hands=True)
    for t_plain, t_para, meta in zip(plain.texts, one.texts, one.meta):
        assert t_para[: len(t_plain)] == t_plain  # the canonical texts come first
        assert len(t_para) > len(t_plain)
        assert intent_of(meta).intent == meta["intent"]
