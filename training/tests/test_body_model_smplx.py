"""The `smplx` backend against a FAKE SMPL-X model file.

The model file written here is synthetic (random arrays with the key names and shapes the
`smplx` loader reads); no SMPL-X data is used or shipped. The reference outputs come from the
installed `smplx` package's own axis-angle ``SMPLX`` model, an independent path from our
rotation-matrix ``SMPLXLayer`` call and our FK.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

smplx = pytest.importorskip("smplx")
trimesh = pytest.importorskip("trimesh")

from comgrasp_train import skeleton as sk  # noqa: E402
from comgrasp_train.body_model import BodyModelConfig, make_body_model  # noqa: E402
from comgrasp_train.body_model_smplx import NUM_VERTICES, SmplxBody  # noqa: E402
from comgrasp_train.rotations import axis_angle_to_matrix  # noqa: E402

V, J = NUM_VERTICES, sk.NUM_JOINTS
N_FACES = 20908


def _fake_model(seed: int) -> dict[str, np.ndarray]:
    """Structurally valid SMPL-X arrays: vertex v belongs to joint cluster v % 55."""
    rng = np.random.default_rng(seed)
    cluster = np.arange(V) % J
    counts = np.bincount(cluster, minlength=J)
    v_template = sk.DEFAULT_REST_JOINTS[cluster] + rng.normal(scale=0.02, size=(V, 3))
    j_reg = np.zeros((J, V))
    j_reg[cluster, np.arange(V)] = 1.0 / counts[cluster]
    # Dense blend weights, 0.6 on the vertex's own joint + 0.4 spread: argmax = own joint.
    w = rng.random((V, J)) ** 8
    w = 0.4 * w / w.sum(1, keepdims=True)
    w[np.arange(V), cluster] += 0.6
    parents = np.asarray(sk.PARENTS, dtype=np.int64)
    parents[0] = 4294967295  # how SMPL-family files mark the root; the loader resets it to -1
    hands = {}
    for side in "lr":
        q, _ = np.linalg.qr(rng.normal(size=(45, 45)))
        hands[f"hands_components{side}"] = q
        hands[f"hands_mean{side}"] = rng.normal(scale=0.3, size=45)  # non-zero: must NOT be added
    return {
        "v_template": v_template,
        "f": rng.integers(0, V, size=(N_FACES, 3)).astype(np.int64),
        "J_regressor": j_reg,
        "weights": w,
        "kintree_table": np.stack([parents, np.arange(J)]),
        # 10 shape + 10 expression components (the loader accepts fewer than 400)
        "shapedirs": rng.normal(scale=1e-3, size=(V, 3, 20)).astype(np.float32),
        "posedirs": (rng.standard_normal((V, 3, (J - 1) * 9), dtype=np.float32) * 2e-3),
        "lmk_faces_idx": rng.integers(0, N_FACES, size=51).astype(np.int64),
        "lmk_bary_coords": rng.dirichlet(np.ones(3), size=51),
        **hands,
    }


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("smplx_models")
    (root / "smplx").mkdir()
    model = _fake_model(0)
    np.savez(root / "smplx" / "SMPLX_MALE.npz", **model)
    # A subject template: the model template, stretched and jittered.
    rng = np.random.default_rng(1)
    vtemp = model["v_template"] * np.array([1.05, 1.08, 0.97]) + rng.normal(scale=0.005, size=(V, 3))
    vtemp_path = root / "s1.ply"
    trimesh.Trimesh(vertices=vtemp, faces=model["f"][:100], process=False).export(vtemp_path)
    vtemp_read = np.asarray(trimesh.load(vtemp_path, process=False, force="mesh").vertices)
    body = SmplxBody(BodyModelConfig(backend="smplx", smplx_model_dir=str(root)), chunk_size=3)
    return {"root": root, "model": model, "vtemp_path": vtemp_path, "vtemp": vtemp_read, "body": body}


def _random_pose(b: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    aa = torch.randn(b, J, 3, generator=g) * 0.4
    transl = torch.randn(b, 3, generator=g)
    return aa, transl


def _reference(fake, aa: torch.Tensor, transl: torch.Tensor):
    """smplx's own axis-angle SMPLX model with the subject template (as GRAB/GOAL use it)."""
    b = aa.shape[0]
    ref = smplx.create(
        model_path=str(fake["root"]), model_type="smplx", gender="male", use_pca=False,
        flat_hand_mean=True, batch_size=b, v_template=torch.tensor(fake["vtemp"], dtype=torch.float32),
    )
    p = aa.reshape(b, -1)
    with torch.no_grad():
        out = ref(global_orient=p[:, 0:3], body_pose=p[:, 3:66], jaw_pose=p[:, 66:69],
                  leye_pose=p[:, 69:72], reye_pose=p[:, 72:75], left_hand_pose=p[:, 75:120],
                  right_hand_pose=p[:, 120:165], transl=transl)
    return out


def test_subject_rest_joints_and_codes(fake):
    subj = fake["body"].subject("male", fake["vtemp_path"])
    assert subj.rest_joints.dtype == torch.float64 and subj.rest_joints.shape == (J, 3)
    expect = fake["model"]["J_regressor"] @ fake["vtemp"]
    np.testing.assert_allclose(subj.rest_joints.numpy(), expect, atol=1e-12)
    # distinct from the model's own template joints: the personalised template is used
    assert np.abs(expect - fake["model"]["J_regressor"] @ fake["model"]["v_template"]).max() > 1e-3
    assert subj.vertex_code.shape == (V,)
    assert subj.vertex_code.min() >= 1 and subj.vertex_code.max() <= 55
    np.testing.assert_array_equal(subj.vertex_code, np.arange(V) % J + 1)
    assert subj.left_hand_mask.any() and subj.right_hand_mask.any() and subj.foot_mask.any()
    assert fake["body"].subject("Male", fake["vtemp_path"]) is subj  # cached, gender normalised


def test_forward_matches_smplx(fake):
    body = fake["body"]
    subj = body.subject("male", fake["vtemp_path"])
    aa, transl = _random_pose(5, 0)
    rot = axis_angle_to_matrix(aa)
    out = body(subj, rot, transl, vertices=True)
    ref = _reference(fake, aa, transl)
    assert out.joints.shape == (5, J, 3) and out.global_rot.shape == (5, J, 3, 3)
    assert out.vertices.shape == (5, V, 3)
    assert (out.joints - ref.joints[:, :J]).abs().max() <= 1e-5
    assert (out.vertices - ref.vertices).abs().max() <= 1e-5  # chunked in 3+2 frames
    # joints-only call matches, and the global rotations are the FK chain's
    out2 = body.forward(subj, rot, transl)
    assert out2.vertices is None
    torch.testing.assert_close(out2.joints, out.joints)
    g_rot, _ = sk.forward_kinematics(rot, subj.rest_joints, transl)
    torch.testing.assert_close(out.global_rot, g_rot)


def test_forward_float64_and_leading_dims(fake):
    body = fake["body"]
    subj = body.subject("male", fake["vtemp_path"])
    aa, transl = _random_pose(4, 1)
    rot = axis_angle_to_matrix(aa.double()).reshape(2, 2, J, 3, 3)
    out = body(subj, rot, transl.double().reshape(2, 2, 3), vertices=True)
    assert out.vertices.dtype == torch.float64 and out.vertices.shape == (2, 2, V, 3)
    ref = _reference(fake, aa, transl)
    assert (out.joints.reshape(4, J, 3) - ref.joints[:, :J]).abs().max() <= 1e-5
    assert (out.vertices.reshape(4, V, 3) - ref.vertices).abs().max() <= 1e-5


def test_missing_vtemp_uses_model_template(fake):
    with pytest.warns(UserWarning, match="template"):
        subj = fake["body"].subject("male", fake["root"] / "does_not_exist.ply")
    expect = fake["model"]["J_regressor"] @ fake["model"]["v_template"]
    np.testing.assert_allclose(subj.rest_joints.numpy(), expect, atol=1e-12)


def test_bad_vtemp_errors(fake, tmp_path):
    small = tmp_path / "small.ply"
    trimesh.creation.icosphere(subdivisions=2).export(small)
    with pytest.raises(ValueError, match="10475"):
        fake["body"].subject("male", small)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"not a ply file at all\x00\x01")
    with pytest.raises(ValueError, match="junk.ply"):
        fake["body"].subject("male", junk)


def test_missing_gender_and_bad_gender(fake):
    with pytest.raises(FileNotFoundError, match="SMPLX_FEMALE.npz"):
        fake["body"].subject("female", fake["vtemp_path"])
    with pytest.raises(ValueError, match="gender"):
        fake["body"].subject("robot", fake["vtemp_path"])


def test_config_errors(tmp_path):
    with pytest.raises(ValueError, match="smplx_model_dir"):
        SmplxBody(BodyModelConfig(backend="smplx"))
    with pytest.raises(FileNotFoundError, match="not a folder"):
        SmplxBody(BodyModelConfig(backend="smplx", smplx_model_dir=str(tmp_path / "nope")))
    with pytest.raises(FileNotFoundError, match=r"smplx/SMPLX_MALE\.npz.*SMPLX_NEUTRAL\.npz"):
        SmplxBody(BodyModelConfig(backend="smplx", smplx_model_dir=str(tmp_path)))


def test_missing_package_error(fake, monkeypatch):
    monkeypatch.setitem(sys.modules, "smplx", None)  # makes `import smplx` raise ImportError
    with pytest.raises(ImportError, match="pip install smplx"):
        SmplxBody(BodyModelConfig(backend="smplx", smplx_model_dir=str(fake["root"])))


def test_make_body_model_and_flat_layout(fake, tmp_path):
    m = make_body_model(BodyModelConfig(backend="smplx", smplx_model_dir=str(fake["root"])))
    assert isinstance(m, SmplxBody) and m.backend == "smplx"
    # the files may also sit directly in the folder (no smplx/ subfolder)
    (tmp_path / "SMPLX_MALE.npz").symlink_to(fake["root"] / "smplx" / "SMPLX_MALE.npz")
    flat = make_body_model(BodyModelConfig(backend="smplx", smplx_model_dir=str(tmp_path)))
    assert flat.model_file("male") == tmp_path / "SMPLX_MALE.npz"
    subj = flat.subject("male", fake["vtemp_path"])
    np.testing.assert_allclose(subj.rest_joints.numpy(), fake["model"]["J_regressor"] @ fake["vtemp"], atol=1e-12)
