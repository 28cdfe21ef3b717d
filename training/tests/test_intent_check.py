"""The prompt checker: prompts parse back to what made them; SynthGrasp's own motions obey
their prompts; corrupted motions (hands swapped, object frozen, pass reversed, contact
dropped) and mismatched prompts do not."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from comgrasp_train.cli.data import main as data_main
from comgrasp_train.dataset import FeatureSet, prepare_features
from comgrasp_train.grab.text import INTENT_PHRASES, describe, hands_from_contact
from comgrasp_train.grab.text_parse import UNKNOWN, Intent, parse_prompt
from comgrasp_train.intent_check import (
    SYNTH_INTENTS,
    check_feature_set,
    check_features,
    check_motion,
    intent_rates,
    object_sdf_for,
    track_from_features,
)
from comgrasp_train.layout import COMPONENT_SLICES, CONTACT_CHANNELS, FIELD
from comgrasp_train.metrics import unheld_object_motion
from comgrasp_train.objects.catalogue import CATALOGUE
from comgrasp_train.synth.generate import INTENTS, generate_dataset

N_SEQUENCES = 18  # three per intent: every hand mode of every intent
SEED = 11


# ---- prompts ------------------------------------------------------------------------------


def _contact(kind: str) -> np.ndarray:
    """(T, 2) [left, right] labels: one hand, both together, or a hand-over."""
    c = np.zeros((30, 2), bool)
    if kind in ("left", "right"):
        c[5:20, ("left", "right").index(kind)] = True
    elif kind == "both":
        c[5:20] = True
    else:  # 'left>right' / 'right>left'
        a, b = (("left", "right").index(s) for s in kind.split(">"))
        c[5:15, a] = True
        c[12:25, b] = True
    return c


def test_every_template_intent_and_hand_phrase_round_trips():
    objects = list(CATALOGUE) + ["alarmclock", "stanfordbunny", "camera"]  # GRAB names too
    for intent in INTENT_PHRASES:
        for gender in ("male", "female", "neutral"):
            for obj in objects:
                for kind in (None, "left", "right", "both", "left>right", "right>left"):
                    contact = None if kind is None else _contact(kind)
                    texts = describe(gender, intent, obj, contact, mention_hands=kind is not None)
                    assert len(texts) == 8
                    want = None
                    if kind is not None:
                        h = hands_from_contact(contact)
                        want = f"{h['first']}>{h['last']}" if intent == "pass" and h["first"] != h["last"] \
                            else h["hands"]
                    for t in texts:
                        assert parse_prompt(t) == Intent(intent, want, obj), t


def test_natural_variants_and_unknown_text():
    assert parse_prompt("  the WOMAN pours from a cup using two hands ") == Intent("pour", "both", "cup")
    assert parse_prompt("A person is lifting the coffee mug in their left hand.") == Intent("lift", "left", "mug")
    assert parse_prompt("A man lifts the cube.") == Intent("lift", None, "cube")  # names three objects
    assert parse_prompt("A man passes the mug from his left hand to his right hand.").hands == "left>right"
    assert parse_prompt("A man passes the mug from his left hand to his left.") == Intent("pass", None, "mug")
    for bad in ("", "hello", "A man is juggling the mug.", "A dog drinks from the cup.", "A man is", None, 42):
        assert parse_prompt(bad) is UNKNOWN, bad  # type: ignore[arg-type]
    assert not UNKNOWN.known and UNKNOWN.sides == ()


def test_the_checker_knows_every_synthgrasp_intent():
    assert SYNTH_INTENTS == INTENTS


def test_unheld_object_motion_from_the_last_held_frame():
    rot = np.tile(np.eye(3), (5, 1, 1))
    pos = np.zeros((5, 3))
    pos[:, 2] = [0.0, 0.0, 1.0, 1.0, 2.0]
    assert unheld_object_motion(rot, pos, np.array([0, 1, 1, 0, 0], bool)) == (1000.0, 0.0)
    assert unheld_object_motion(rot, pos, np.ones(5, bool)) == (0.0, 0.0)


# ---- motions ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synth(tmp_path_factory, one_thread_module):
    """A small SynthGrasp set as prepared features (hands named), and its prompts' intents."""
    root = tmp_path_factory.mktemp("sg")
    generate_dataset(root, N_SEQUENCES, SEED, workers=1, progress=False)
    fs, _ = prepare_features(root, None, "all", mention_hands=True)
    return root, fs


@pytest.fixture(scope="module")
def one_thread_module():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: threads only contend
    yield
    torch.set_num_threads(n)


def _check(fs, i, x=None, intent: Intent | None = None):
    track = track_from_features(fs.features[i] if x is None else x, fs.rest_joints[i], fs.fps,
                                object_sdf_for(fs.meta[i]))
    return check_motion(track, intent or parse_prompt(fs.texts[i][0]))


def _swap_hands(x: np.ndarray) -> np.ndarray:
    """Left and right hand features exchanged (finger rotations, wrist offset, contact)."""
    y = x.copy()
    left, right = COMPONENT_SLICES["lhand"], COMPONENT_SLICES["rhand"]
    y[:, left], y[:, right] = x[:, right], x[:, left]
    return y


def test_ground_truth_obeys_its_prompts(synth):
    _, fs = synth
    results = check_feature_set(fs)
    assert all(r.intent.intent == m["intent"] for r, m in zip(results, fs.meta))
    assert {r.intent.hands for r in results} >= {"left", "right", "both", "left>right", "right>left"}
    failed = [(fs.texts[i][0], r.reason) for i, r in enumerate(results) if not r.ok]
    assert not failed
    rates = intent_rates(results)
    assert rates["intent_ok"] == 1.0 and set(rates) == {"intent_ok", "intent_grasp", "intent_unheld_still",
                                                        *(f"intent_{k}" for k in SYNTH_INTENTS)}
    # Every prompt template checks the same.
    for i in range(0, len(fs), 5):
        assert all(check_features(fs.features[i], t, fs.meta[i], fs.rest_joints[i], fs.fps).ok for t in fs.texts[i])


def test_swapped_hands_fail_the_named_hand(synth):
    _, fs = synth
    for i, m in enumerate(fs.meta):
        r = _check(fs, i, _swap_hands(fs.features[i]))
        if m["hands"] == "both" and m["intent"] != "pass":
            continue  # both hands named, both still flagged
        assert not r.ok, fs.texts[i][0]
        assert not r.rules["grasp"] or not r.rules.get("pass", True), (fs.texts[i][0], r.reason)


def test_the_wrong_hand_in_the_prompt_fails(synth):
    _, fs = synth
    for i in range(len(fs)):
        it = parse_prompt(fs.texts[i][0])
        if it.hands in ("left", "right"):
            other = "right" if it.hands == "left" else "left"
            r = _check(fs, i, intent=replace(it, hands=other))
            assert not r.rules["grasp"] and "grasp" in r.reason
        elif it.hands in ("left>right", "right>left"):
            r = _check(fs, i, intent=replace(it, hands=">".join(it.hands.split(">")[::-1])))
            assert not r.rules["pass"] and r.rules["grasp"]


def test_a_frozen_object_does_not_lift(synth):
    _, fs = synth
    lifts = [i for i, m in enumerate(fs.meta) if m["intent"] == "lift"]
    assert lifts
    obj = slice(FIELD["object_rot6d"].start, FIELD["object_centre"].stop)
    for i in lifts:
        x = fs.features[i].copy()
        x[:, obj] = x[:1, obj]
        r = _check(fs, i, x)
        assert not r.rules["lift"] and "lift" in r.reason


def test_a_reversed_pass_fails(synth):
    _, fs = synth
    passes = [i for i, m in enumerate(fs.meta) if m["intent"] == "pass"]
    assert passes
    for i in passes:
        r = _check(fs, i, fs.features[i][::-1].copy())
        assert r.rules["grasp"] and not r.rules["pass"], r.reason


def test_no_contact_while_the_object_moves_fails(synth):
    _, fs = synth
    for i in range(len(fs)):
        x = fs.features[i].copy()
        x[:, list(CONTACT_CHANNELS)] = 0.0
        r = _check(fs, i, x)
        assert not r.rules["grasp"] and not r.rules["unheld_still"] and not r.ok
        assert r.values["unheld_mm"] > 50


def test_contact_flags_far_from_the_object_do_not_hold(synth):
    """The flag alone is not a grasp: the object shifted 30 cm away with the flags kept."""
    _, fs = synth
    i = 0
    x = fs.features[i].copy()
    x[:, FIELD["object_transl"].slice] += np.array([0.0, 0.0, 0.3], np.float32)
    assert not _check(fs, i, x).rules["grasp"]


def test_other_intents_rules_reject_a_lift(synth):
    _, fs = synth
    for i, m in enumerate(fs.meta):
        if m["intent"] != "lift":
            continue
        it = parse_prompt(fs.texts[i][0])
        for other in ("drink", "pour", "inspect"):
            r = _check(fs, i, intent=replace(it, intent=other))
            assert not r.rules[other], (other, r.values)


def test_cli_check_intent(synth, capsys):
    root, _ = synth
    assert data_main(["-q", "check-intent", str(root), "--limit", "6"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("intent_ok 1.000 (6/6)")


def test_evaluate_reports_prompt_checks(synth):
    """evaluate_generation adds the 0/1 prompt checks per sample; an oracle model that
    returns the ground truth obeys every prompt, the ground truth's row too."""
    from comgrasp_train.evaluate import evaluate_generation, evaluate_ground_truth_intent, summarize_repeats

    _, fs = synth
    texts = {t[0]: i for i, t in enumerate(fs.texts)}

    class Oracle:
        def generate(self, prompts, params, seed=0):
            return [fs.features[texts[p]] for p in prompts]

    reps = evaluate_generation(Oracle(), fs, repeats=1, limit=4)["raw"]
    assert all(row["intent_ok"] == 1.0 and "mpjpe_mm" in row for row in reps[0])
    assert summarize_repeats(reps)["intent_ok"].mean == 1.0
    gt = evaluate_ground_truth_intent(fs, limit=4)
    assert len(gt) == 4 and all(row["intent_ok"] == 1.0 and row["intent_grasp"] == 1.0 for row in gt)


def test_a_flickering_flag_is_not_a_release_and_short_touches_are_not_grasps():
    from comgrasp_train.intent_check import MotionTrack, hold_masks

    T = 60
    contact = np.zeros((T, 2), bool)
    contact[10:40, 0] = True
    contact[20:22, 0] = False  # a 2-frame dropout
    contact[45:50, 0] = True  # 1/6 s: a touch
    contact[0:3, 1] = True
    track = MotionTrack(np.zeros((T, 55, 3)), np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3)), contact, 30.0,
                        lambda p: np.linalg.norm(p, axis=-1) - 0.05)
    held, gripped = hold_masks(track)
    assert (held == contact).all()
    assert np.array_equal(np.nonzero(gripped[:, 0])[0], np.arange(10, 40)) and not gripped[:, 1].any()


def test_grasp_offsets_are_each_grasping_wrist_at_its_first_flag_from_the_resting_object():
    from comgrasp_train import skeleton as sk
    from comgrasp_train.intent_check import MotionTrack, grasp_offsets

    T = 12
    joints = np.random.default_rng(0).normal(size=(T, 55, 3))
    transl = np.zeros((T, 3))
    transl[:] = (0.1, 0.5, 0.9)
    transl[5:] += (0.0, 0.0, 0.3)  # lifted later: the offset is from where it rested
    contact = np.zeros((T, 2), bool)
    contact[7:10, 1] = True  # the right hand grasps later than the left
    contact[4:11, 0] = True
    joints[4, sk.LEFT_WRIST] = (0.1, 0.4, 1.0)
    joints[7, sk.RIGHT_WRIST] = (0.25, 0.5, 0.85)
    track = MotionTrack(joints, np.tile(np.eye(3), (T, 1, 1)), transl, contact, 30.0, lambda p: p[..., 0])
    assert np.allclose(grasp_offsets(track), [(0.0, -0.1, 0.1), (0.15, 0.0, -0.05)])
    contact[:, 0] = False
    assert np.allclose(grasp_offsets(track), [(0.15, 0.0, -0.05)])
    assert grasp_offsets(MotionTrack(joints, track.object_rot, transl, np.zeros((T, 2), bool), 30.0,
                                     track.object_sdf)).shape == (0, 3)


def test_a_track_without_the_shape_gives_grasp_offsets_and_refuses_shape_queries(synth):
    from comgrasp_train.intent_check import grasp_offsets

    _, fs = synth
    i = 0
    bare = track_from_features(fs.features[i], fs.rest_joints[i], fs.fps)
    full = track_from_features(fs.features[i], fs.rest_joints[i], fs.fps, object_sdf_for(fs.meta[i]))
    assert len(grasp_offsets(bare)) > 0 and np.array_equal(grasp_offsets(bare), grasp_offsets(full))
    with pytest.raises(ValueError, match="without the object's shape"):
        check_motion(bare, parse_prompt(fs.texts[i][0]))


def _engine_frames(fs, i) -> dict:
    """What `comgrasp generate --fk --out F.npz` writes for a motion (native coordinates,
    quaternions x, y, z, w), built from a prepared sequence."""
    from comgrasp_train.representation import features_to_joints, features_to_params
    from comgrasp_train.rotations import matrix_to_quaternion

    x, rest = fs.features[i], torch.as_tensor(fs.rest_joints[i], dtype=torch.float64)
    p = features_to_params(x, rest)
    q = matrix_to_quaternion(torch.as_tensor(p["object_rotmat"])).numpy()[:, [1, 2, 3, 0]]  # (w,x,y,z) -> xyzw
    return {"joint_positions": features_to_joints(torch.as_tensor(x, dtype=torch.float64), rest).numpy(),
            "object_rotation": q, "object_translation": p["object_transl"], "contact": p["contact"].astype(np.uint8),
            "fps": np.array(fs.fps)}


def test_engine_frames_check_like_the_features(synth, tmp_path):
    from comgrasp_train.cli.data import main as data_main
    from comgrasp_train.intent_check import intent_of, track_from_engine

    _, fs = synth
    for i in range(len(fs.features)):
        sdf = object_sdf_for(fs.meta[i])
        want = _check(fs, i)
        track = track_from_engine(_engine_frames(fs, i), sdf)
        ref = track_from_features(fs.features[i], fs.rest_joints[i], fs.fps, sdf)
        np.testing.assert_allclose(track.object_rot, ref.object_rot, atol=1e-6)  # x, y, z, w read right
        got = check_motion(track, want.intent)
        assert got.rules == want.rules and got.ok, (fs.texts[i][0], got.reason)
        assert intent_of(fs.meta[i]) == want.intent
    # The CLI: a passing file; frames without --fk or an unreadable prompt are clear errors.
    frames = _engine_frames(fs, 0)
    good, nofk = tmp_path / "good.npz", tmp_path / "nofk.npz"
    np.savez(good, **frames)
    np.savez(nofk, **{k: v for k, v in frames.items() if k != "joint_positions"})
    report = tmp_path / "r.json"
    assert data_main(["-q", "check-engine", str(good), "--prompt", fs.texts[0][0], "--json", str(report)]) == 0
    assert json.loads(report.read_text())["rates"]["intent_ok"] == 1.0
    assert data_main(["-q", "check-engine", str(nofk), "--prompt", fs.texts[0][0]]) == 2
    assert data_main(["-q", "check-engine", str(good), "--prompt", "dance a little"]) == 2
    # --meaning: a wording the parser does not read is checked against what it asks for.
    it = intent_of(fs.meta[0])
    meaning = f"{it.intent} {it.object} {it.hands or 'none'}"
    assert data_main(["-q", "check-engine", str(good), "--prompt", "dance a little", "--meaning", meaning,
                      "--json", str(report)]) == 0
    assert json.loads(report.read_text())["rates"]["intent_ok"] == 1.0
    assert it.hands in ("left", "right"), it  # one hand holds it: the other asked for fails
    other = "left" if it.hands == "right" else "right"
    assert data_main(["-q", "check-engine", str(good), "--prompt", "dance a little", "--meaning",
                      f"{it.intent} {it.object} {other}", "--json", str(report)]) == 0
    assert json.loads(report.read_text())["rates"]["intent_ok"] == 0.0
    assert data_main(["-q", "check-engine", str(good), "--prompt", "x", "--meaning", "lift mug"]) == 2


class _StandInVQ(torch.nn.Module):
    """Decodes what it encodes, one frame per token; ``freeze_object`` holds the decoded
    object at its first frame's pose (a VQ that cannot move the object)."""

    frames_per_token = 1

    def __init__(self, freeze_object: bool):
        super().__init__()
        self.freeze_object = freeze_object
        self.device_anchor = torch.nn.Parameter(torch.zeros(()))  # evaluate reads the device from it

    def encode(self, x):
        return x

    def decode(self, x):
        if not self.freeze_object:
            return x
        y = x.clone()
        for f in ("object_transl", "object_rot6d"):
            s = FIELD[f].slice
            y[:, :, s] = x[:, :1, s]
        return y


def test_reconstruction_reports_the_prompt_checks_of_what_it_decodes(synth):
    """evaluate_reconstruction checks each decoded motion against its sequence's prompt: an
    exact VQ obeys every prompt, one that cannot move the object fails every lift."""
    from comgrasp_train.evaluate import evaluate_reconstruction
    from comgrasp_train.normalization import Normalizer

    _, full = synth
    norm = Normalizer.fit(full.features)
    first = list({m["intent"]: i for i, m in reversed(list(enumerate(full.meta)))}.values())  # one per intent
    fs = FeatureSet(full.fps, *([getattr(full, k)[i] for i in first] for k in ("features", "rest_joints", "texts", "meta")))
    assert sorted(m["intent"] for m in fs.meta) == sorted(SYNTH_INTENTS)
    exact = evaluate_reconstruction(_StandInVQ(False), norm, fs)["raw"]
    assert all(row["intent_ok"] == 1.0 and row["mpjpe_mm"] < 1.0 for row in exact)
    frozen = evaluate_reconstruction(_StandInVQ(True), norm, fs)["raw"]
    for row, m in zip(frozen, fs.meta):
        assert row["intent_ok"] == 0.0, m["intent"]
        if m["intent"] == "lift":
            assert row["intent_lift"] == 0.0
