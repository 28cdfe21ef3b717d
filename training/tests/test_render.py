"""The renderer writes valid GIFs/PNG strips whose frames follow the motion."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image, ImageChops

from comgrasp_train import skeleton as sk
from comgrasp_train.body_model import BodyModelConfig, OpenSkeletonBody
from comgrasp_train.grab.reader import GrabSequence
from comgrasp_train.render import ObjectGeometry, render_arrays, render_sequence, table_top

T = 5
pytestmark = pytest.mark.filterwarnings("ignore:open body model")  # default skeleton, no subject file


@pytest.fixture()
def seq(tmp_path):
    """A standing subject (root turned to z up) lowering the left arm onto a lifted cube."""
    trimesh.creation.box(extents=(0.06, 0.06, 0.06)).export(tmp_path / "cube.ply")
    table = trimesh.creation.box(extents=(1.2, 0.8, 0.04))
    table.apply_translation((0.0, 0.0, -0.02))
    table.export(tmp_path / "table.ply")
    fp = np.zeros((T, 55, 3), np.float32)
    fp[:, 0, 0] = np.pi / 2
    fp[:, 16, 2] = -np.linspace(0.0, 0.9, T)
    ot = np.tile(np.float32([0.7, -0.25, 0.8]), (T, 1))
    ot[:, 2] += np.linspace(0.0, 0.2, T, dtype=np.float32)
    eye = np.tile(np.eye(3, dtype=np.float32), (T, 1, 1))
    return GrabSequence(
        path=str(tmp_path / "s1" / "cube_lift.npz"), sbj_id="s1", gender="male", obj_name="cube", intent="lift",
        framerate=30.0, fullpose=fp, transl=np.tile(np.float32([0.0, 0.0, 1.295]), (T, 1)),
        object_rotmat=eye, object_transl=ot, object_mesh=str(tmp_path / "cube.ply"), vtemp="",
        contact=np.stack([np.arange(T) >= 3, np.zeros(T, bool)], -1),
        table_rotmat=eye, table_transl=np.tile(np.float32([0.4, -0.3, 0.78]), (T, 1)),
        table_mesh=str(tmp_path / "table.ply"),
    )


@pytest.fixture(scope="module")
def body():
    return OpenSkeletonBody(BodyModelConfig())


def test_gif_frames_follow_motion(seq, body, tmp_path):
    out = render_sequence(seq, body, tmp_path / "out" / "a.gif", fps=30)
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == T
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(im.convert("RGB"))
    assert ImageChops.difference(frames[0], frames[-1]).getbbox() is not None


def test_png_strip(seq, body, tmp_path):
    out = render_sequence(seq, body, tmp_path / "strip.png", strip=True)
    with Image.open(out) as im:
        assert im.format == "PNG" and im.width > 3 * im.height  # several panels side by side
        rgb = np.asarray(im.convert("RGB")).astype(int)
    # Contact is drawn red in the later panels only (panel count = T here: 5 frames).
    red = (rgb[..., 0] > 200) & (rgb[..., 1] < 60) & (rgb[..., 2] < 60)
    w = rgb.shape[1] // T
    per_panel = [red[:, k * w:(k + 1) * w].sum() for k in range(T)]
    assert per_panel[0] == 0 and per_panel[-1] > 0


def test_render_arrays_without_object_and_frame_cap(tmp_path):
    joints = np.repeat(sk.DEFAULT_REST_JOINTS[None, :, [0, 2, 1]], 40, 0)  # y-up rest turned z-up
    joints[:, :, 0] += np.linspace(0, 0.5, 40)[:, None]
    out = render_arrays(joints, tmp_path / "b.gif", src_fps=30, fps=30, max_frames=4, size=2.0)
    with Image.open(out) as im:
        assert im.n_frames == 4


def test_object_geometry_and_table_top():
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.1))
    geo = ObjectGeometry.from_mesh(box)
    assert geo.faces is not None and len(geo.faces) == 12
    dense = ObjectGeometry.from_mesh(trimesh.creation.icosphere(4), max_faces=100, max_points=50)
    assert dense.faces is None and len(dense.vertices) == 50
    top = table_top(box, np.eye(3), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(top[:, 2], 1.05)
    np.testing.assert_allclose(top[:, :2].min(0), [-0.5, -0.25])
