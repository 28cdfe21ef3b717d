"""335-D representation: build -> invert round trips, resampling, normalization, feature sets."""

from __future__ import annotations

import numpy as np
import torch

from comgrasp_train import skeleton as sk
from comgrasp_train.body_model import BodyModelConfig, make_body_model
from comgrasp_train.dataset import FeatureSet, prepare_features
from comgrasp_train.grab.reader import load_sequence
from comgrasp_train.grab.splits import get_split
from comgrasp_train.layout import COMPONENT_SLICES, FIELD, FRAME_DIM
from comgrasp_train.normalization import Normalizer
from comgrasp_train.representation import (
    build_features,
    features_to_joints,
    features_to_params,
    object_centre_local,
    resample_sequence,
)
from comgrasp_train.rotations import axis_angle_to_matrix


def _fk(fullpose, transl, rest):
    rot = axis_angle_to_matrix(torch.as_tensor(fullpose, dtype=torch.float64).reshape(-1, 55, 3))
    return sk.forward_kinematics(rot, rest.double(), torch.as_tensor(transl, dtype=torch.float64))[1]


def _seq_and_rest(grab_root):
    seq = load_sequence(grab_root / "grab" / "s1" / "mug_drink_0.npz", grab_root)
    rest = torch.from_numpy(sk.scaled_rest_joints(sk.Proportions(height=1.07, arm=0.95, hand=1.1)))
    return seq, rest


def test_round_trip_to_parameters_and_fk_joints(grab_root):
    seq, rest = _seq_and_rest(grab_root)
    s30 = resample_sequence(seq, 30)
    assert s30.n_frames == 12 and s30.framerate == 30
    np.testing.assert_array_equal(s30.fullpose, seq.fullpose[::4])
    x = build_features(s30, rest)
    assert x.shape == (12, FRAME_DIM) and x.dtype == np.float32
    p = features_to_params(x, rest)
    j_orig = _fk(s30.fullpose, s30.transl, rest)
    j_back = _fk(p["fullpose"], p["transl"], rest)
    assert (j_orig - j_back).norm(dim=-1).max() < 1e-5  # metres
    # Differentiable FK straight from features gives the same joints.
    assert (features_to_joints(torch.from_numpy(x).double(), rest) - j_orig).norm(dim=-1).max() < 1e-5
    np.testing.assert_allclose(p["object_rotmat"], s30.object_rotmat, atol=1e-5)
    np.testing.assert_allclose(p["object_transl"], s30.object_transl, atol=1e-6)
    np.testing.assert_array_equal(p["contact"], s30.contact)
    # GRAB-convention object orientation inverts to the file's own values.
    raw = np.load(seq.path, allow_pickle=True)["object"].item()["params"]["global_orient"][::4]
    back = axis_angle_to_matrix(torch.from_numpy(p["object_global_orient"]))
    np.testing.assert_allclose(back.numpy(), axis_angle_to_matrix(torch.from_numpy(raw).double()).numpy(), atol=1e-5)


def test_wrist_vectors_and_object_centre(grab_root):
    seq, rest = _seq_and_rest(grab_root)
    x = build_features(seq, rest).astype(np.float64)
    j = _fk(seq.fullpose, seq.transl, rest).numpy()
    c_local = np.array(object_centre_local(seq.object_mesh))
    centre = np.einsum("tij,j->ti", seq.object_rotmat.astype(np.float64), c_local) + seq.object_transl
    np.testing.assert_allclose(x[:, FIELD["object_centre"].slice], centre, atol=1e-5)
    np.testing.assert_allclose(x[:, FIELD["lwrist_to_object"].slice], j[:, 20] - centre, atol=1e-5)
    np.testing.assert_allclose(x[:, FIELD["rwrist_to_object"].slice], j[:, 21] - centre, atol=1e-5)
    np.testing.assert_allclose(x[:, FIELD["root_transl"].slice], j[:, 0], atol=1e-5)
    assert set(np.unique(x[:, [240, 334]])) <= {0.0, 1.0}
    assert [s.stop - s.start for s in COMPONENT_SLICES.values()] == [21, 126, 94, 94]


def test_resampling_to_a_non_divisor_rate_interpolates(grab_root):
    seq, rest = _seq_and_rest(grab_root)
    s = resample_sequence(seq, 50)  # 120 / 50 is not an integer
    assert s.n_frames == int((seq.n_frames - 1) / 120 * 50) + 1
    # Frame k of the 50 fps sequence sits at 120-fps time 2.4 k: frame 5 -> source frame 12 exactly.
    np.testing.assert_allclose(
        _fk(s.fullpose[5:6], s.transl[5:6], rest), _fk(seq.fullpose[12:13], seq.transl[12:13], rest), atol=1e-5)
    np.testing.assert_allclose(s.object_rotmat[5], seq.object_rotmat[12], atol=1e-5)
    # Interpolated poses stay between their neighbours (joint positions).
    mid = _fk(s.fullpose[1:2], s.transl[1:2], rest)[0]
    a, b = _fk(seq.fullpose[2:4], seq.transl[2:4], rest)
    assert ((mid - a).norm(dim=-1) <= (b - a).norm(dim=-1) + 1e-4).all()


def test_normalizer_fit_save_load(tmp_path):
    rng = np.random.default_rng(1)
    feats = [rng.normal(3.0, 2.0, (100, FRAME_DIM)).astype(np.float32) for _ in range(3)]
    for f in feats:
        f[:, [240, 334]] = rng.integers(0, 2, (100, 2))
        f[:, 30] = 1.5  # a constant channel
    n = Normalizer.fit(feats)
    assert abs(n.mean[5] - 3.0) < 0.3 and abs(n.std[5] - 2.0) < 0.3
    assert n.mean[240] == 0 and n.std[334] == 1 and n.std[30] > 0
    x = n.normalize(feats[0])
    np.testing.assert_array_equal(x[:, [240, 334]], feats[0][:, [240, 334]])
    np.testing.assert_allclose(n.denormalize(x), feats[0], atol=1e-5)
    n.save(tmp_path / "stats.npz")
    m = Normalizer.load(tmp_path / "stats.npz")
    np.testing.assert_array_equal(m.mean, n.mean)
    assert (tmp_path / "stats.json").is_file()


def test_prepare_feature_set(grab_root, tmp_path):
    fs, summary = prepare_features(grab_root, get_split("diffgrasp"), "train", fps=30,
                                   body=BodyModelConfig(), mention_hands=True)
    assert summary.loaded == 3 and len(fs) == 3
    assert all(f.shape[1] == FRAME_DIM for f in fs.features)
    k = [m["name"] for m in fs.meta].index("s1/mug_drink_0")
    assert fs.meta[k]["intent"] == "drink" and fs.texts[k][0].startswith("A man is drinking from the mug")
    fs.save(tmp_path / "train.npz")
    back = FeatureSet.load(tmp_path / "train.npz")
    assert back.texts == fs.texts and back.meta == fs.meta and back.fps == 30
    for a, b in zip(back.features, fs.features):
        np.testing.assert_array_equal(a, b)
    assert make_body_model().subject("male", None).rest_joints.shape == (55, 3)


def test_spread_takes_the_subjects_in_turn():
    """A limit on a split listed subject by subject covers every subject (evaluate --limit)."""
    subjects = ["s9"] * 5 + ["s10"] * 2 + ["s11"] * 3
    fs = FeatureSet(30.0, [np.full((4, 335), i, np.float32) for i in range(10)], [np.zeros((55, 3))] * 10,
                    [[f"t{i}"] for i in range(10)], [{"subject": s, "i": i} for i, s in enumerate(subjects)])
    five = fs.spread(5)
    assert [m["i"] for m in five.meta] == [0, 1, 5, 6, 7]  # s9, s10, s11, then s9 and s10 again, in set order
    assert [float(f[0, 0]) for f in five.features] == [0, 1, 5, 6, 7] and five.texts[2] == ["t5"]
    assert [m["i"] for m in fs.spread(8).meta] == [0, 1, 2, 5, 6, 7, 8, 9]  # s10 runs out, the others go on
    assert fs.spread(None) is fs and fs.spread(10) is fs and len(fs.spread(0)) == 0
