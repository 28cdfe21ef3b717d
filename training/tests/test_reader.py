"""The GRAB reader on fixtures written in GRAB's exact format, including broken ones."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from comgrasp_train.grab.reader import GrabFormatError, load_dataset, load_sequence
from comgrasp_train.grab.splits import SPLITS, get_split
from comgrasp_train.grab.text import describe, hands_from_contact
from comgrasp_train.rotations import axis_angle_to_matrix


def test_loads_the_published_layout(grab_root):
    f = grab_root / "grab" / "s1" / "mug_drink_0.npz"
    raw = np.load(f, allow_pickle=True)
    assert all(raw[k].ndim == 0 for k in raw.files)  # every entry is a 0-d array, as in GRAB
    seq = load_sequence(f, grab_root)
    body = raw["body"].item()["params"]
    assert seq.fullpose.shape == (48, 55, 3)
    np.testing.assert_allclose(seq.fullpose.reshape(48, 165), body["fullpose"])
    # Object rotation: GRAB's row convention v @ R + t becomes a column rotation R^T.
    R = axis_angle_to_matrix(torch.from_numpy(raw["object"].item()["params"]["global_orient"]).double()).numpy()
    np.testing.assert_allclose(seq.object_rotmat, np.swapaxes(R, -1, -2), atol=1e-6)
    v = np.array([0.1, -0.2, 0.3])
    np.testing.assert_allclose(seq.object_rotmat[5] @ v, v @ R[5], atol=1e-6)
    assert seq.object_mesh.endswith("tools/object_meshes/contact_meshes/mug.ply")
    # Contact codes: 22 (right palm) in frames 12..23, 27 (left index) in frames 16..31.
    assert seq.contact[12:24, 1].all() and not seq.contact[:12, 1].any() and not seq.contact[24:, 1].any()
    assert seq.contact[16:32, 0].all() and not seq.contact[:16, 0].any()


def test_intent_comes_from_motion_intent_not_the_file_name(grab_root, tmp_path):
    root = tmp_path / "g"
    shutil.copytree(grab_root / "tools", root / "tools")
    src = np.load(grab_root / "grab" / "s1" / "mug_drink_0.npz", allow_pickle=True)
    entries = {k: src[k] for k in src.files}
    entries["motion_intent"] = np.array("switchON")
    (root / "grab" / "s1").mkdir(parents=True)
    np.savez(root / "grab" / "s1" / "mug_on_1.npz", **entries)
    seq = load_sequence(root / "grab" / "s1" / "mug_on_1.npz", root)
    assert seq.intent == "switchON"
    assert describe("male", seq.intent, "flashlight")[0] == "A man is switching on the flashlight."


def _broken_copy(grab_root, tmp_path, mutate):
    root = tmp_path / "broken"
    shutil.copytree(grab_root, root)
    src = np.load(grab_root / "grab" / "s1" / "mug_drink_0.npz", allow_pickle=True)
    entries = {k: src[k] for k in src.files}
    entries = {k: (v.item() if v.dtype == object else v) for k, v in entries.items()}
    mutate(entries)
    out = {k: (np.array(v, dtype=object) if isinstance(v, dict) else v) for k, v in entries.items()}
    bad = root / "grab" / "s1" / "mug_drink_0.npz"
    np.savez(bad, **out)
    return root, bad


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda e: e.pop("contact"), "missing key 'contact'"),
        (lambda e: e.pop("motion_intent"), "missing key 'motion_intent'"),
        (lambda e: e["body"]["params"].pop("fullpose"), "missing key 'body/params/fullpose'"),
        (lambda e: e["body"]["params"].__setitem__("transl", np.zeros((48, 2))), "'body/params/transl' has shape (48, 2)"),
        (lambda e: e["object"]["params"].__setitem__("transl", np.zeros((47, 3))), "'object/params/transl' has shape (47, 3)"),
        (lambda e: e["contact"].__setitem__("object", np.zeros((48, 7), np.int8)), "'contact/object' has shape (48, 7)"),
        (lambda e: e["object"].__setitem__("object_mesh", "tools/object_meshes/contact_meshes/nope.ply"), "is unreadable"),
        (lambda e: e.__setitem__("n_frames", np.array(99)), "'n_frames' is 99"),
        (lambda e: e["body"]["params"]["fullpose"].__setitem__((3, 4), np.nan), "NaN"),
    ],
)
def test_broken_files_are_skipped_with_a_clear_message(grab_root, tmp_path, mutate, message):
    root, bad = _broken_copy(grab_root, tmp_path, mutate)
    with pytest.raises(GrabFormatError) as err:
        load_sequence(bad, root)
    assert str(bad) in str(err.value) and message in str(err.value)
    seqs, summary = load_dataset(root, part="all")
    assert summary.skipped == 1 and summary.loaded == 5 and len(seqs) == 5
    assert message in summary.problems[0]


def test_not_an_npz_and_unreadable_mesh_file(grab_root, tmp_path):
    root = tmp_path / "g2"
    shutil.copytree(grab_root, root)
    (root / "grab" / "s3" / "junk_lift_9.npz").write_bytes(b"not a zip")
    (root / "tools/object_meshes/contact_meshes/cubesmall.ply").write_bytes(b"ply\ngarbage")
    seqs, summary = load_dataset(root, part="all")
    assert summary.skipped == 4 and summary.loaded == 3
    assert any("not a readable npz" in p for p in summary.problems)
    assert sum("cubesmall.ply is unreadable" in p for p in summary.problems) == 3


def test_named_splits(grab_root):
    assert get_split("diffgrasp").subjects("test") == ["s10"]
    assert get_split("saga").subjects("test") == ["s9", "s10"]
    assert len(get_split("paper").subjects("train")) == 8 and len(get_split("paper").subjects("test")) == 2
    with pytest.raises(ValueError):
        get_split("nope")
    train, _ = load_dataset(grab_root, SPLITS["diffgrasp"], "train")
    test, _ = load_dataset(grab_root, SPLITS["diffgrasp"], "test")
    assert {s.sbj_id for s in train} == {"s1", "s3"} and {s.sbj_id for s in test} == {"s10"}
    saga_test, _ = load_dataset(grab_root, SPLITS["saga"], "test")
    assert {s.sbj_id for s in saga_test} == {"s9", "s10"}
    unseen, _ = load_dataset(grab_root, SPLITS["diffgrasp_unseen"], "all")
    assert len(unseen) == 6  # 'all' ignores the split's filters


def test_text_templates():
    texts = describe("male", "takepicture", "camera")
    assert "A man is taking a picture with a camera." in texts
    assert len(set(texts)) == len(texts) >= 4
    c = np.zeros((10, 2), bool)
    c[2:6, 0] = True
    c[5:9, 1] = True
    assert hands_from_contact(c) == {"hands": "both", "first": "left", "last": "right"}
    passing = describe("female", "pass", "apple", c, mention_hands=True)
    assert "The woman passes the apple from her left hand to her right." in passing
    lifting = describe("female", "lift", "mug", c * np.array([True, False]), mention_hands=True)
    assert "A woman lifts the mug with her left hand." in lifting
    assert describe("male", "lift", "waterbottle")[0] == "A man is lifting the water bottle."
