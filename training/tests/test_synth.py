"""SynthGrasp: the generated files are GRAB files, deterministic and physically consistent.

Every physical check goes through what a consumer sees: the reader's arrays, the open body
model built from the written ``_skeleton.npy`` and the object's analytic shape file; not the
generator's internals.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from comgrasp_train.body_model import BodyModelConfig, OpenSkeletonBody
from comgrasp_train.grab.format import LEFT_HAND_CODES, RIGHT_HAND_CODES
from comgrasp_train.grab.reader import load_dataset
from comgrasp_train.objects.shapes import Shape
from comgrasp_train.rotations import axis_angle_to_matrix
from comgrasp_train.surface import pose_points
from comgrasp_train.synth.generate import INDEX_FILE, generate_dataset, generate_sequence, plan_dataset

N_SEQUENCES = 18  # three per intent: covers every hand mode of every intent
SEED = 7
WRISTS = {0: 20, 1: 21}  # reader contact column -> wrist joint
HAND_CODES = {0: LEFT_HAND_CODES, 1: RIGHT_HAND_CODES}
THRESHOLD = float(np.sqrt(2e-5))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthgrasp")
    summary = generate_dataset(root, N_SEQUENCES, SEED, workers=1, progress=False)
    seqs, load = load_dataset(root, part="all", keep_vertex_contact=True)
    return root, summary, seqs, load


@pytest.fixture(scope="module")
def posed(dataset):
    """Per sequence: the body-model subject, joints and global rotations of every frame."""
    body = OpenSkeletonBody(BodyModelConfig())
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: threads only contend
    try:
        out = []
        for seq in dataset[2]:
            subj = body.subject(seq.gender, seq.vtemp)
            rot = axis_angle_to_matrix(torch.from_numpy(seq.fullpose).double())
            o = body(subj, rot, torch.from_numpy(seq.transl).double())
            out.append((subj, o.joints.numpy(), o.global_rot.numpy()))
    finally:
        torch.set_num_threads(threads)
    return out


def _points(subj, joints, global_rot, mask):
    """Posed proxy points (T, n, 3) of the points selected by ``mask``."""
    rest = subj.rest_joints
    return pose_points(subj.extra["proxy_joint"][mask], subj.extra["proxy_rest"][mask], rest,
                       torch.from_numpy(global_rot), torch.from_numpy(joints)).numpy()


def _segments(flags: np.ndarray):
    """(start, stop) of each run of True."""
    d = np.diff(np.concatenate([[0], flags.astype(int), [0]]))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def test_reader_loads_every_file_and_the_index_matches(dataset):
    root, summary, seqs, load = dataset
    assert load.skipped == 0 and load.loaded == N_SEQUENCES == summary["sequences"]
    index = json.loads((root / INDEX_FILE).read_text())
    rows = {r["file"]: r for r in index["files"]}
    model = OpenSkeletonBody(BodyModelConfig())
    for seq in seqs:
        row = rows[str(Path(seq.path).relative_to(root))]
        assert (row["sbj_id"], row["gender"], row["obj_name"], row["intent"]) == (
            seq.sbj_id, seq.gender, seq.obj_name, seq.intent)
        assert row["n_frames"] == seq.n_frames and seq.framerate == 120
        assert Path(seq.vtemp).is_file() and Path(seq.vtemp[:-4] + "_skeleton.npy").is_file()
        # The hands the index names are the hands the contact labels say held the object.
        used = {h for h, k in (("left", 0), ("right", 1)) if seq.contact[:, k].any()}
        assert used == set(row["hands"])
        raw = np.load(seq.path, allow_pickle=True)
        assert all(raw[k].ndim == 0 for k in raw.files)
        contact = raw["contact"].item()
        body = model.subject(seq.gender, seq.vtemp)
        assert contact["body"].shape == (seq.n_frames, len(body.vertex_code))
        on = contact["body"] != 0  # contact/body holds the touching proxy point's own code
        assert np.array_equal(contact["body"][on], np.broadcast_to(body.vertex_code, on.shape)[on])


def test_coverage_and_lengths(dataset):
    root, summary, seqs, _ = dataset
    index = json.loads((root / INDEX_FILE).read_text())
    assert set(summary["intent"]) == {"lift", "pass", "offhand", "inspect", "drink", "pour"}
    assert set(summary["hands"]) == {"left", "right", "both", "left>right", "right>left"}
    assert len(summary["subject"]) == 10 and set(summary["gender"]) == {"male", "female"}
    assert all(2.0 <= r["seconds"] <= 12.0 for r in index["files"])
    for seq in seqs:
        assert 2.0 <= (seq.n_frames - 1) / seq.framerate <= 12.0


def test_same_seed_same_bytes(dataset, tmp_path):
    root = dataset[0]
    spec = plan_dataset(N_SEQUENCES, SEED)[1]  # generate_dataset made it in the same process
    shutil.copytree(root / "tools", tmp_path / "tools")
    generate_sequence(spec, tmp_path, SEED)
    assert (tmp_path / spec.file).read_bytes() == (root / spec.file).read_bytes()
    generate_sequence(spec, tmp_path, SEED + 1)
    assert (tmp_path / spec.file).read_bytes() != (root / spec.file).read_bytes()


def test_feet_are_planted_on_the_floor(posed):
    for subj, joints, g in posed:
        feet = joints[:, [7, 8, 10, 11]]
        assert np.abs(feet - feet[:1]).max() < 1e-3
        foot_pts = _points(subj, joints[::30], g[::30], subj.foot_mask)
        assert np.abs(foot_pts[..., 2].min(axis=1)).max() < 1e-3


def test_object_rests_on_the_table_unless_held(dataset):
    for seq in dataset[2]:
        verts = np.asarray(trimesh.load(seq.object_mesh, process=False).vertices)
        free = ~seq.contact.any(axis=1)
        assert free[0] and free[-1] and (~free).any()
        for a, b in _segments(free):
            rot, pos = seq.object_rotmat[a:b], seq.object_transl[a:b]
            assert np.abs(rot - rot[0]).max() < 1e-6 and np.abs(pos - pos[0]).max() < 1e-6
            bottom = (verts @ rot[0].astype(np.float64).T + pos[0])[:, 2].min()
            assert abs(bottom - seq.table_transl[a, 2]) < 1e-3


def test_holding_hand_carries_the_object_rigidly_and_touches_it(dataset, posed):
    worst = {"drift": 0.0, "angle": 0.0, "penetration": 0.0, "gap": 0.0, "label_mismatch": 0.0}
    for seq, (subj, joints, g) in zip(dataset[2], posed):
        shape = Shape.load(seq.object_mesh[:-4] + ".shape.json")
        verts = np.asarray(trimesh.load(seq.object_mesh, process=False).vertices)
        codes = seq.object_contact_codes
        for k in (0, 1):
            hand = subj.mask(HAND_CODES[k])
            for a, b in _segments(seq.contact[:, k]):
                w_rot, w_pos = g[a:b, WRISTS[k]], joints[a:b, WRISTS[k]]
                o_rot, o_pos = seq.object_rotmat[a:b].astype(np.float64), seq.object_transl[a:b].astype(np.float64)
                rel_rot = np.swapaxes(w_rot, -1, -2) @ o_rot
                rel_pos = np.einsum("tji,tj->ti", w_rot, o_pos - w_pos)
                worst["drift"] = max(worst["drift"], np.abs(rel_pos - rel_pos[0]).max())
                cos = (np.trace(np.swapaxes(rel_rot[0], -1, -2) @ rel_rot, axis1=-2, axis2=-1) - 1) / 2
                worst["angle"] = max(worst["angle"], np.arccos(np.clip(cos, -1, 1)).max())
                frames = np.arange(a, b, 20)
                pts = _points(subj, joints[frames], g[frames], hand)
                local = np.einsum("tji,tpj->tpi", seq.object_rotmat[frames].astype(np.float64),
                                  pts - seq.object_transl[frames, None].astype(np.float64))
                sdf = shape.sdf(local)
                worst["penetration"] = max(worst["penetration"], -sdf.min())
                worst["gap"] = max(worst["gap"], sdf.min(axis=1).max())
                # contact/object: the vertices within GRAB's threshold of this hand carry its codes
                # (with both hands on it, the nearer hand's); vertices within 0.1 mm of the
                # threshold may go either way (float32 files).
                for f, p in zip(frames, local):
                    dist = cKDTree(p).query(verts)[0]
                    near, sure = dist <= THRESHOLD, np.abs(dist - THRESHOLD) > 1e-4
                    labelled = np.isin(codes[f], list(HAND_CODES[k]))
                    wrong = labelled & ~near if seq.contact[f].all() else labelled != near
                    worst["label_mismatch"] = max(worst["label_mismatch"], int((wrong & sure).sum()))
                    assert labelled.any()
    assert worst["drift"] < 1e-3 and worst["angle"] < 2e-3, worst
    assert worst["penetration"] <= 5e-3 and worst["gap"] <= 2.5e-3, worst
    assert worst["label_mismatch"] == 0, worst


def test_metric_suite_on_the_generated_batch(dataset):
    """The ground truth through the paper's metric suite (what `comgrasp-data check` reports):
    bounds stated here are the SynthGrasp contract."""
    from comgrasp_train.plausibility import dataset_plausibility

    rep = dataset_plausibility(dataset[0], limit=None)
    assert rep["skipped"] == 0 and rep["sequences"] >= 6
    worst, mean = rep["max"], rep["mean"]
    assert worst["foot_sliding_mm"] < 0.01  # mm per frame: feet planted
    assert worst["object_unheld_motion_mm"] < 0.01 and worst["object_unheld_rotation_deg"] < 0.1
    assert worst["penetration_max_mm"] < 10.0  # any body point, deepest over all frames
    assert mean["penetration_max_mm"] < 3.0
    assert mean["label_contact_f1"] > 0.9  # contact labels agree with geometric contact (5 mm)


def test_held_out_subjects_lie_inside_the_training_subjects_range():
    """A validation or test subject of the `synthgrasp` split is a new person of the training
    population: every proportion inside the training subjects' range (one taller than all of
    them made the VQ extrapolate the pelvis height: docs/training.md, "Held-out subjects")."""
    from dataclasses import astuple

    from comgrasp_train.grab.splits import get_split
    from comgrasp_train.synth.subjects import SUBJECT

    split = get_split("synthgrasp")
    props = lambda ids: np.array([astuple(SUBJECT[s].proportions) for s in ids])  # noqa: E731
    train = props(split.subjects("train"))
    lo, hi = train.min(0), train.max(0)
    for part in ("val", "test"):
        for sid, p in zip(split.subjects(part), props(split.subjects(part))):
            assert np.all((p >= lo) & (p <= hi)), f"{part} subject {sid}: {p} outside the training range {lo}..{hi}"
