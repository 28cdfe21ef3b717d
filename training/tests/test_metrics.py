"""Known-answer tests of the metric suite and the object SDFs (small synthetic inputs)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from comgrasp_train import metrics as M
from comgrasp_train import skeleton as sk
from comgrasp_train.body_model import BodyModelConfig, OpenSkeletonBody
from comgrasp_train.grab.reader import GrabSequence
from comgrasp_train.objects import sdf as S
from comgrasp_train.objects.shapes import Part, Shape

R_SPHERE = 0.05
SPHERE_OFFSET = np.array([0.03, 0.0, 0.0])  # sphere centre in the object frame
OBJ_ROT = Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix()  # catches R vs R^T mix-ups


@pytest.fixture(scope="module")
def body():
    model = OpenSkeletonBody(BodyModelConfig())
    return model, model.subject_from_rest(sk.DEFAULT_REST_JOINTS, key="default")


@pytest.fixture(scope="module")
def sphere_sdf():
    shape = Shape((Part("sphere", {"r": R_SPHERE}, tuple(SPHERE_OFFSET)),))
    return S.ShapeSDF(shape, radius=R_SPHERE + 0.03)


@pytest.fixture(scope="module")
def tpose_left_tip(body):
    """Posed T-pose points and the left hand's extreme +x point (the hand points along +x)."""
    model, subj = body
    joints, verts = M.run_body_model(model, subj, torch.eye(3).expand(1, 55, 3, 3), torch.zeros(1, 3))
    left = np.isin(subj.vertex_code, list(M.LEFT_HAND_CODES))
    pts = verts[0][left].astype(np.float64)
    return pts[pts[:, 0].argmax()]


def _object_pose_for_gap(tip: np.ndarray, gaps: list[float]):
    """Object poses putting the sphere's surface ``gap`` beyond the tip along +x (negative =
    pushed in). Every hand point has x <= tip x, so the hand's min SDF is exactly ``gap``."""
    centres = np.array([tip + np.array([R_SPHERE + g, 0.0, 0.0]) for g in gaps])
    rot = np.repeat(OBJ_ROT[None], len(gaps), 0)
    return rot, centres - rot @ SPHERE_OFFSET


def _sample(body, sdf, rotmats, transl, obj_rot, obj_t, contact=None, fps=30.0):
    model, subj = body
    return M.sample_from_pose(model, subj, rotmats, transl, obj_rot, obj_t, sdf, fps, contact)


def _tpose(T):
    return torch.eye(3, dtype=torch.float64).expand(T, 55, 3, 3).clone(), np.zeros((T, 3))


def _random_pose(T, seed=0):
    g = torch.Generator().manual_seed(seed)
    aa = 0.15 * torch.randn(T, 55, 3, generator=g, dtype=torch.float64)
    from comgrasp_train.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(aa), np.cumsum(np.full((T, 3), 0.01), 0)


def _shifted(s: M.MotionSample, joints=None, vertices=None, object_transl=None) -> M.MotionSample:
    return dataclasses.replace(
        s, joints=s.joints if joints is None else joints, vertices=s.vertices if vertices is None else vertices,
        object_transl=s.object_transl if object_transl is None else object_transl,
    )


# ---- the suite ----------------------------------------------------------------------------


def test_self_comparison_is_perfect(body, sphere_sdf, tpose_left_tip):
    rot, t = _tpose(6)
    orot, ot = _object_pose_for_gap(tpose_left_tip, [0.0, 0.0, 0.0, 0.05, 0.05, 0.05])
    s = _sample(body, sphere_sdf, rot, t, orot, ot)
    m = M.compute_metrics(s, s)
    for k in ("h_mpjpe_mm", "mpjpe_mm", "mpvpe_mm", "collision_pct", "collision_depth_mm", "contact_distance_mm"):
        assert m[k] == pytest.approx(0.0, abs=1e-6), k
    assert m["contact_f1"] == 1.0 and m["contact_precision"] == 1.0 and m["contact_recall"] == 1.0
    assert m["foot_sliding_mm"] == m["foot_sliding_gt_mm"]
    assert set(M.METRIC_KEYS) <= set(m)


def test_no_contact_on_either_side_gives_f1_one():
    assert M.contact_scores(np.zeros((5, 2), bool), np.zeros((5, 2), bool))["contact_f1"] == 1.0
    assert M.contact_scores(np.ones((5, 2), bool), np.zeros((5, 2), bool))["contact_f1"] == 0.0


def test_rigid_shift_of_everything(body, sphere_sdf, tpose_left_tip):
    rot, t = _random_pose(5)
    orot, ot = _object_pose_for_gap(tpose_left_tip, [0.0] * 5)
    gt = _sample(body, sphere_sdf, rot, t, orot, ot)
    u = np.array([0.006, 0.0, 0.008])  # 10 mm
    pred = _shifted(gt, gt.joints + u, gt.vertices + u.astype(np.float32), gt.object_transl + u)
    m = M.compute_metrics(pred, gt)
    assert m["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)
    assert m["mpvpe_mm"] == pytest.approx(0.0, abs=1e-3)
    assert m["h_mpjpe_mm"] == pytest.approx(10.0, abs=1e-6)
    assert m["contact_f1"] == 1.0
    assert m["collision_pct"] == pytest.approx(m["collision_pct_gt"])


def test_shift_of_one_hands_fingers(body, sphere_sdf, tpose_left_tip):
    rot, t = _random_pose(4, seed=1)
    orot, ot = _object_pose_for_gap(tpose_left_tip, [0.1] * 4)
    gt = _sample(body, sphere_sdf, rot, t, orot, ot)
    j = gt.joints.copy()
    j[:, list(sk.LEFT_HAND_JOINTS)] += np.array([0.0, 0.01, 0.0])
    m = M.compute_metrics(_shifted(gt, joints=j), gt)
    assert m["h_mpjpe_mm"] == pytest.approx(15 * 10.0 / 32, abs=1e-6)
    assert m["mpjpe_mm"] == pytest.approx(15 * 10.0 / 52, abs=1e-6)
    wrists_only = M.MetricConfig(hand_joints=(sk.LEFT_WRIST, sk.RIGHT_WRIST))
    assert M.compute_metrics(_shifted(gt, joints=j), gt, wrists_only)["h_mpjpe_mm"] == pytest.approx(0.0, abs=1e-9)


def test_hand_pushed_into_sphere(body, sphere_sdf, tpose_left_tip):
    d = 0.012
    rot, t = _tpose(4)
    orot, ot = _object_pose_for_gap(tpose_left_tip, [-d, -d, 0.05, 0.05])
    s = _sample(body, sphere_sdf, rot, t, orot, ot)
    m = M.compute_metrics(s, s)
    assert m["collision_pct"] == pytest.approx(50.0)
    assert m["collision_depth_mm"] == pytest.approx(d * 1000, abs=0.5)
    pushed = _sample(body, sphere_sdf, rot[:2], t[:2], orot[:2], ot[:2])
    assert M.compute_metrics(pushed, pushed)["collision_pct"] == 100.0
    # Shallower than the 5 mm threshold: no collision, but counted by plausibility.
    orot, ot = _object_pose_for_gap(tpose_left_tip, [-0.003] * 2)
    shallow = _sample(body, sphere_sdf, rot[:2], t[:2], orot, ot)
    assert M.collision(M.surface_stats(shallow))[0] == 0.0
    assert M.plausibility(shallow)["penetration_max_mm"] == pytest.approx(3.0, abs=0.01)


def test_contact_touching_vs_two_cm(body, sphere_sdf, tpose_left_tip):
    rot, t = _tpose(4)
    touch = _sample(body, sphere_sdf, rot, t, *_object_pose_for_gap(tpose_left_tip, [0.0] * 4))
    away = _sample(body, sphere_sdf, rot, t, *_object_pose_for_gap(tpose_left_tip, [0.02] * 4))
    half = _sample(body, sphere_sdf, rot, t, *_object_pose_for_gap(tpose_left_tip, [0.0, 0.0, 0.02, 0.02]))
    m = M.compute_metrics(away, touch)
    assert m["contact_f1"] == 0.0 and m["contact_recall"] == 0.0
    assert m["contact_distance_mm"] == pytest.approx(20.0, abs=1e-3)
    assert m["contact_accuracy"] == pytest.approx(0.5)  # the right hand is correctly free
    m = M.compute_metrics(half, touch)
    assert m["contact_f1"] == pytest.approx(2 / 3)
    assert m["contact_precision"] == 1.0 and m["contact_recall"] == 0.5
    assert m["contact_distance_mm"] == pytest.approx(10.0, abs=1e-3)
    m = M.compute_metrics(touch, touch)
    assert m["contact_f1"] == 1.0 and m["contact_distance_mm"] == pytest.approx(0.0, abs=1e-6)
    assert math.isnan(M.compute_metrics(touch, away)["contact_distance_mm"])
    # Against labels instead of the reference's geometry.
    labelled = dataclasses.replace(away, contact=np.array([[1, 0], [1, 0], [0, 0], [0, 0]], bool))
    m = M.compute_metrics(half, labelled, M.MetricConfig(gt_contact="labels"))
    assert m["contact_f1"] == 1.0


def _feet(T, left_speed, right_speed, ankle_h=0.06, toe_h=0.0, floor=0.0):
    j = np.zeros((T, 55, 3))
    for ankle, toe, v in ((sk.LEFT_ANKLE, sk.LEFT_FOOT, left_speed), (sk.RIGHT_ANKLE, sk.RIGHT_FOOT, right_speed)):
        x = v * np.arange(T)
        j[:, ankle] = np.stack([x, np.full(T, 0.1), np.full(T, floor + ankle_h)], -1)
        j[:, toe] = np.stack([x + 0.1, np.full(T, 0.1), np.full(T, floor + toe_h)], -1)
    return j


def test_foot_sliding_known_value():
    T, v = 20, 0.004  # right foot slides 4 mm per frame, below the 5 mm/frame static speed
    j = _feet(T, 0.0, v, floor=0.3)
    assert M.floor_height(j, 30.0) == pytest.approx(0.3)
    ankle = 1000 / T * (T - 1) * v * (2 - 2 ** (0.06 / 0.08))
    toe = 1000 / T * (T - 1) * v * 1.0
    assert M.foot_sliding(j, 30.0) == pytest.approx((ankle + toe) / 4)
    # Feet above H never slide.
    assert M.foot_sliding(_feet(T, v, v, ankle_h=0.09, toe_h=0.05), 30.0, floor=0.0) == 0.0
    # The static-speed threshold scales with fps: 4 mm/frame at 120 fps is not static.
    j2 = _feet(T, 0.0, v, floor=0.0)
    j2[:, sk.LEFT_FOOT, 2] = 0.02  # static left toe: the floor
    j2[:, sk.RIGHT_FOOT, 2] = 0.0
    assert M.floor_height(j2, 30.0) == pytest.approx(0.01)  # median over both static toes
    assert M.floor_height(j2, 120.0) == pytest.approx(0.02)  # the right toe is moving now


def test_plausibility_object_moving_unheld(body, sphere_sdf, tpose_left_tip):
    rot, t = _tpose(6)
    orot, ot = _object_pose_for_gap(tpose_left_tip, [0.1, 0.1, -0.003, -0.003, 0.017, 0.017])
    labels = np.array([[0, 0], [0, 0], [1, 0], [1, 0], [0, 0], [0, 0]], bool)
    s = _sample(body, sphere_sdf, rot, t, orot, ot, contact=labels)
    p = M.plausibility(s)
    assert p["object_unheld_motion_mm"] == pytest.approx(20.0, abs=1e-6)  # from the last held frame
    assert p["object_unheld_rotation_deg"] == pytest.approx(0.0, abs=1e-4)
    assert p["penetration_max_mm"] == pytest.approx(3.0, abs=0.01)
    assert p["penetration_mean_mm"] == pytest.approx(1.0, abs=0.01)
    assert p["label_contact_f1"] == 1.0
    assert p["contact_frames_pct"] == pytest.approx(100 * 2 / 6)


def test_summaries():
    rows = [{"a": 1.0, "b": math.nan}, {"a": 3.0, "b": 2.0}]
    s = M.summarize(rows)
    assert s["a"].mean == 2.0 and s["a"].n == 2
    assert s["a"].ci95 == pytest.approx(1.96 * np.std([1, 3], ddof=1) / math.sqrt(2))
    assert s["b"].mean == 2.0 and s["b"].n == 1 and s["b"].ci95 == 0.0
    r = M.summarize_repeats([rows, [{"a": 5.0, "b": 4.0}]])
    assert r["a"].mean == pytest.approx(3.5) and r["a"].n == 2


def test_sample_from_sequence(body, tmp_path):
    model, _ = body
    shape = Shape((Part("box", {"hx": 0.03, "hy": 0.03, "hz": 0.03}),))
    shape.mesh(0.02).export(tmp_path / "cube.ply")
    (tmp_path / "cube.shape.json").write_text(shape.to_json())
    T = 3
    fp = np.zeros((T, 55, 3), np.float32)
    fp[:, 0, 0] = np.pi / 2
    seq = GrabSequence(
        path=str(tmp_path / "s1" / "cube_lift.npz"), sbj_id="s1", gender="male", obj_name="cube", intent="lift",
        framerate=30.0, fullpose=fp, transl=np.tile(np.float32([0.0, 0.0, 1.0]), (T, 1)),
        object_rotmat=np.tile(np.eye(3, dtype=np.float32), (T, 1, 1)), object_transl=np.zeros((T, 3), np.float32),
        object_mesh=str(tmp_path / "cube.ply"), vtemp="", contact=np.zeros((T, 2), bool),
    )
    with pytest.warns(UserWarning):
        s = M.sample_from_sequence(seq, OpenSkeletonBody(BodyModelConfig()))
    assert isinstance(s.object_sdf, S.ShapeSDF)
    assert s.joints.shape == (T, 55, 3) and s.vertices.shape[0] == T and s.fps == 30.0
    pelvis = sk.DEFAULT_REST_JOINTS[0]
    np.testing.assert_allclose(s.joints[0, 0], pelvis + [0.0, 0.0, 1.0], atol=1e-6)  # FK: J_0 + transl
    assert s.joints[0, sk.HEAD, 2] > s.joints[0, sk.LEFT_FOOT, 2] + 1.0  # z up after the root turn


# ---- object SDFs --------------------------------------------------------------------------


def test_grid_sdf_matches_sphere_near_surface():
    mesh = trimesh.creation.icosphere(3, radius=R_SPHERE)
    g = S.build_grid_sdf(mesh.vertices, mesh.faces, resolution=40)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    p = dirs * (R_SPHERE + rng.uniform(-0.01, 0.01, (2000, 1)))
    exact = np.linalg.norm(p, axis=1) - R_SPHERE
    assert np.abs(g.sdf(p) - exact).max() < 1e-3
    # Outside the padded box: distance to the box plus the grid value, exact along an axis.
    assert g.sdf(np.array([0.5, 0.0, 0.0])) == pytest.approx(0.45, abs=1e-3)


@pytest.mark.parametrize("kind", ["box", "torus"])
def test_grid_sdf_sign(kind):
    if kind == "box":
        mesh = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
        inside = np.array([[0, 0, 0], [0.045, 0.025, 0.015], [-0.04, 0.0, -0.01]])
        outside = np.array([[0.06, 0, 0], [0, 0.04, 0], [0, 0, 0.03], [0.3, 0.3, 0.3]])
    else:
        mesh = trimesh.creation.torus(0.05, 0.015, major_sections=48, minor_sections=24)
        inside = np.array([[0.05, 0, 0], [0, -0.05, 0], [0.035 * np.sqrt(0.5), 0.05 * np.sqrt(0.5), 0.005]])
        outside = np.array([[0, 0, 0], [0.02, 0, 0], [0.05, 0, 0.025], [0.08, 0, 0]])
    g = S.build_grid_sdf(mesh.vertices, mesh.faces, resolution=32)
    assert (g.sdf(inside) < 0).all()
    assert (g.sdf(outside) > 0).all()


def test_load_object_sdf_cache_and_shape(tmp_path, monkeypatch):
    mesh = trimesh.creation.icosphere(2, radius=0.04)
    mesh.export(tmp_path / "ball.ply")
    cache = tmp_path / "cache"
    first = S.load_object_sdf(tmp_path / "ball.ply", cache_dir=cache, resolution=24)
    assert isinstance(first, S.GridSDF) and len(list(cache.glob("*.npz"))) == 1
    S._LOADED.clear()
    monkeypatch.setattr(S, "build_grid_sdf", lambda *a, **k: pytest.fail("cache not used"))
    second = S.load_object_sdf(tmp_path / "ball.ply", cache_dir=cache, resolution=24)
    np.testing.assert_array_equal(first.grid, second.grid)
    assert second.radius == pytest.approx(0.04)
    # With a .shape.json beside the mesh, the analytic SDF wins.
    (tmp_path / "ball.shape.json").write_text(Shape((Part("sphere", {"r": 0.04}),)).to_json())
    exact = S.load_object_sdf(tmp_path / "ball.ply", cache_dir=cache)
    assert isinstance(exact, S.ShapeSDF)
    assert exact(np.array([[0.1, 0.0, 0.0]]))[0] == pytest.approx(0.06)
