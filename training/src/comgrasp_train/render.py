"""Quick-look renders of grasp motions: an animated GIF or a PNG strip of key frames.

Matplotlib (Agg) 3D, z up, no GPU or display needed: the body skeleton as lines (fingers
thinner), the object mesh moved by its pose each frame, the table top, and each hand drawn
red while it is in contact. Axis limits are fixed over the sequence so motion reads as
motion. :func:`render_arrays` draws any motion given as arrays (e.g. a model's output);
:func:`render_sequence` runs the body model on a GRAB/SynthGrasp sequence and calls it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import trimesh
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
from PIL import Image

from . import skeleton as sk

_FACE_JOINTS = (22, 23, 24)
BODY_BONES = tuple((sk.PARENTS[j], j) for j in range(1, 22))
FINGER_BONES = tuple((sk.PARENTS[j], j) for j in (*sk.LEFT_HAND_JOINTS, *sk.RIGHT_HAND_JOINTS))
_SIDE_COLOURS = ("#1f5fa8", "#2a8c4a")  # left, right
_CENTRE_COLOUR = "#444444"
_CONTACT_COLOUR = "#e0161b"
_MAX_OBJECT_FACES = 1500  # more faces are drawn as a point cloud (3D polygons are slow)


def _side(j: int) -> int:
    """0 left, 1 right, -1 centre (from the joint name)."""
    name = sk.JOINT_NAMES[j]
    return 0 if name.startswith("left") else 1 if name.startswith("right") else -1


@dataclass
class ObjectGeometry:
    """An object mesh in its own frame, reduced for drawing."""

    vertices: np.ndarray  # (N, 3)
    faces: np.ndarray | None  # (F, 3), or None to draw the vertices as points

    @staticmethod
    def from_mesh(mesh, max_faces: int = _MAX_OBJECT_FACES, max_points: int = 1200) -> ObjectGeometry:
        """``mesh``: a path, a trimesh, or a (vertices, faces) pair."""
        if isinstance(mesh, (str, Path)):
            mesh = trimesh.load(mesh, force="mesh", process=False)
        v, f = (mesh.vertices, mesh.faces) if isinstance(mesh, trimesh.Trimesh) else mesh
        v = np.asarray(v, dtype=np.float64)
        if f is not None and len(f) <= max_faces:
            return ObjectGeometry(v, np.asarray(f, dtype=np.int64))
        pick = np.linspace(0, len(v) - 1, min(max_points, len(v))).astype(np.int64)
        return ObjectGeometry(v[pick], None)


def table_top(mesh, rotmat: np.ndarray, transl: np.ndarray, tol: float = 0.01) -> np.ndarray:
    """The table's top as a horizontal rectangle (4, 3) in the world, from its mesh and pose."""
    if isinstance(mesh, (str, Path)):
        mesh = trimesh.load(mesh, force="mesh", process=False)
    v = np.asarray(mesh.vertices) @ np.asarray(rotmat, dtype=np.float64).T + np.asarray(transl, dtype=np.float64)
    z = v[:, 2].max()
    top = v[v[:, 2] > z - tol]
    (x0, y0), (x1, y1) = top[:, :2].min(0), top[:, :2].max(0)
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


def _limits(points: np.ndarray, margin: float = 0.1) -> np.ndarray:
    """A cube (3, 2) around all points, so the aspect is equal and fixed over the sequence."""
    lo, hi = points.min(0), points.max(0)
    c, half = (lo + hi) / 2, (hi - lo).max() / 2 + margin
    return np.stack([c - half, c + half], -1)


def _frame_indices(T: int, src_fps: float, fps: float, max_frames: int, strip: bool, n_strip: int) -> np.ndarray:
    if strip:
        return np.unique(np.round(np.linspace(0, T - 1, min(n_strip, T))).astype(np.int64))
    idx = np.arange(0, T, max(1, int(round(src_fps / fps))))
    if len(idx) > max_frames:
        idx = idx[np.round(np.linspace(0, len(idx) - 1, max_frames)).astype(np.int64)]
    return idx


class _Scene:
    """Everything needed to draw any frame; one drawing routine serves GIF and strip."""

    def __init__(self, joints, obj, obj_rot, obj_t, contact, top, title, src_fps):
        self.joints = np.asarray(joints, dtype=np.float64)
        T = len(self.joints)
        self.obj = obj
        self.obj_world = None
        if obj is not None:
            R = np.broadcast_to(np.asarray(obj_rot, dtype=np.float64), (T, 3, 3))
            t = np.broadcast_to(np.asarray(obj_t, dtype=np.float64), (T, 3))
            self.obj_world = np.einsum("tij,vj->tvi", R, obj.vertices) + t[:, None]
        self.contact = np.zeros((T, 2), bool) if contact is None else np.asarray(contact, bool)
        self.title, self.src_fps = title, src_fps
        pts = [self.joints.reshape(-1, 3)]
        if self.obj_world is not None:
            pts.append(self.obj_world.reshape(-1, 3))
        self.lim = _limits(np.concatenate(pts))
        self.top = None
        if top is not None:
            top = np.asarray(top, dtype=np.float64).copy()
            top[:, 0] = np.clip(top[:, 0], *self.lim[0])  # keep the quad inside the view box
            top[:, 1] = np.clip(top[:, 1], *self.lim[1])
            self.top = top

    def draw(self, ax, t: int, view: tuple[float, float], fontsize: float) -> None:
        ax.cla()
        ax.set_xlim(*self.lim[0])
        ax.set_ylim(*self.lim[1])
        ax.set_zlim(*self.lim[2])
        ax.set_box_aspect((1, 1, 1), zoom=1.25)
        ax.view_init(elev=view[0], azim=view[1])
        ax.set_xticklabels([])
        ax.set_yticklabels([])
        ax.set_zticklabels([])
        J = self.joints[t]
        if self.top is not None:
            ax.add_collection3d(Poly3DCollection([self.top], facecolor="#b8b0a0", alpha=0.35, edgecolor="#8a8272"))
        if self.obj_world is not None:
            v = self.obj_world[t]
            if self.obj.faces is not None:
                ax.add_collection3d(Poly3DCollection(v[self.obj.faces], facecolor="#d9a441", alpha=0.55,
                                                     edgecolor="#9c7020", linewidths=0.1))
            else:
                ax.scatter(v[:, 0], v[:, 1], v[:, 2], s=1.5, c="#c98f1e", depthshade=False)
        for bones, width in ((BODY_BONES, 2.4), (FINGER_BONES, 0.9)):
            segs = [(J[a], J[b]) for a, b in bones]
            ax.add_collection3d(Line3DCollection(segs, colors=[self._colour(t, b) for _, b in bones], linewidths=width))
        for side, wrist in enumerate((sk.LEFT_WRIST, sk.RIGHT_WRIST)):
            if self.contact[t, side]:
                ax.scatter(*J[wrist], s=30, c=_CONTACT_COLOUR, depthshade=False)
        ax.scatter(*J[sk.HEAD], s=60, c=_CENTRE_COLOUR, depthshade=False)
        ax.set_title(f"{self.title}\nframe {t + 1}/{len(self.joints)}  t={t / self.src_fps:.2f}s",
                     fontsize=fontsize)

    def _colour(self, t: int, j: int) -> str:
        side = _side(j)
        if side < 0:
            return _CENTRE_COLOUR
        hand = sk.LEFT_HAND_JOINTS if side == 0 else sk.RIGHT_HAND_JOINTS
        if self.contact[t, side] and (j in hand or j in (sk.LEFT_WRIST, sk.RIGHT_WRIST)):
            return _CONTACT_COLOUR
        return _SIDE_COLOURS[side]


def _to_image(fig) -> Image.Image:
    fig.canvas.draw()
    return Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())


def render_arrays(
    joints: np.ndarray,
    out_path: str | Path,
    *,
    object_mesh=None,
    object_rotmat: np.ndarray | None = None,
    object_transl: np.ndarray | None = None,
    contact: np.ndarray | None = None,
    table: np.ndarray | None = None,
    title: str = "",
    src_fps: float = 30.0,
    fps: float = 15.0,
    strip: bool = False,
    max_frames: int = 150,
    n_strip: int = 6,
    view: tuple[float, float] = (18.0, -65.0),
    size: float = 4.8,
    dpi: int = 80,
) -> Path:
    """Render joints (T, 55, 3) (world, z up) with an optional object and table.

    ``object_mesh``: path, trimesh or (vertices, faces) in the object frame, moved by
    ``object_rotmat`` (T, 3, 3) (column convention) and ``object_transl`` (T, 3);
    ``contact`` (T, 2) bool [left, right]; ``table`` the top rectangle (4, 3) (see
    :func:`table_top`). Writes a looping GIF at about ``fps`` (at most ``max_frames``
    frames, played back in real time) or, with ``strip``, one PNG of ``n_strip`` key frames.
    """
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    joints = np.asarray(joints)
    if joints.ndim != 3 or joints.shape[1:] != (sk.NUM_JOINTS, 3):
        raise ValueError(f"joints must be (T, 55, 3), got {joints.shape}")
    obj = None
    if object_mesh is not None:
        obj = ObjectGeometry.from_mesh(object_mesh)
        object_rotmat = np.eye(3) if object_rotmat is None else object_rotmat
        object_transl = np.zeros(3) if object_transl is None else object_transl
    scene = _Scene(joints, obj, object_rotmat, object_transl, contact, table, title, src_fps)
    idx = _frame_indices(len(joints), src_fps, fps, max_frames, strip, n_strip)
    if strip:
        fig = plt.figure(figsize=(size * 0.75 * len(idx), size), dpi=dpi)
        for k, t in enumerate(idx):
            scene.draw(fig.add_subplot(1, len(idx), k + 1, projection="3d"), int(t), view, fontsize=8)
        fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92, wspace=0.0)
        _to_image(fig).save(out_path)
        plt.close(fig)
        return out_path
    fig = plt.figure(figsize=(size, size), dpi=dpi)
    ax = fig.add_subplot(111, projection="3d")
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92)
    frames = []
    for t in idx:
        scene.draw(ax, int(t), view, fontsize=9)
        frames.append(_to_image(fig).convert("P", palette=Image.Palette.ADAPTIVE, colors=128))
    plt.close(fig)
    step = (idx[1] - idx[0]) if len(idx) > 1 else 1
    duration = max(20, int(round(1000.0 * step / src_fps)))
    frames[0].save(out_path, save_all=True, append_images=frames[1:], duration=duration, loop=0, disposal=2)
    return out_path


def render_sequence(seq, body_model, out_path: str | Path, fps: float = 15.0, strip: bool = False,
                    max_frames: int = 150, **kwargs) -> Path:
    """Render a :class:`~comgrasp_train.grab.reader.GrabSequence` (see :func:`render_arrays`)."""
    from .metrics import run_body_model
    from .rotations import axis_angle_to_matrix

    subject = body_model.subject(seq.gender, seq.vtemp or None)
    rotmats = axis_angle_to_matrix(torch.as_tensor(seq.fullpose, dtype=torch.float64))
    joints, _ = run_body_model(body_model, subject, rotmats, seq.transl, vertices=False)
    table = None
    if seq.table_mesh and Path(seq.table_mesh).is_file() and seq.table_rotmat is not None:
        table = table_top(seq.table_mesh, seq.table_rotmat[0], seq.table_transl[0])
    kwargs.setdefault("title", f"{seq.name} ({seq.intent})")
    return render_arrays(joints, out_path, object_mesh=seq.object_mesh, object_rotmat=seq.object_rotmat,
                         object_transl=seq.object_transl, contact=seq.contact, table=table,
                         src_fps=seq.framerate, fps=fps, strip=strip, max_frames=max_frames, **kwargs)
