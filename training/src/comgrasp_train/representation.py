"""The 335-D frame representation (DESIGN §2): build it from a sequence, invert it.

Choices the DESIGN leaves open, fixed here (and mirrored in the bundle manifest):
* ``root_transl`` (6:9) is the world position of the pelvis joint (``J_0 + transl``), not
  SMPL-X's ``transl``: it is what a host's root bone needs and it does not depend on the
  subject. Inverting needs the subject's rest pelvis ``J_0``.
* Object rotation (9:15) is the COLUMN-vector world rotation ``R_w`` (``v_world = R_w v + t``),
  i.e. the transpose of GRAB's row-convention matrix.
* The object centre (18:21) is the world position of the object mesh's bounding-box centre.
* Jaw and eyes are not modelled; inversion sets them to identity.
* Sequences are resampled to the target fps by striding when the source rate is a multiple
  of it (GRAB 120 -> 30: every 4th frame), otherwise by slerp/linear interpolation.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
import torch
import trimesh

from . import rotations as rot
from . import skeleton as sk
from .grab.reader import GrabSequence
from .layout import FIELD, FRAME_DIM, ROT6D_JOINT_COLUMNS

_MODELLED_JOINTS = tuple(sorted(ROT6D_JOINT_COLUMNS))  # 0..21, 25..54
_ROT_COLS = torch.tensor([ROT6D_JOINT_COLUMNS[j] for j in _MODELLED_JOINTS])


@lru_cache(maxsize=256)
def object_centre_local(mesh_path: str) -> tuple[float, float, float]:
    """Bounding-box centre of an object mesh in its own frame (cached per file)."""
    m = trimesh.load(mesh_path, process=False, force="mesh")
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    return tuple(float(x) for x in (lo + hi) / 2.0)


def resample_sequence(seq: GrabSequence, fps: float) -> GrabSequence:
    """The sequence at ``fps``; strides for integer ratios, interpolates otherwise."""
    ratio = seq.framerate / fps
    T = seq.n_frames
    if abs(ratio - round(ratio)) < 1e-6 and round(ratio) >= 1:
        idx = np.arange(0, T, int(round(ratio)))
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        return replace(
            seq, framerate=float(fps), fullpose=seq.fullpose[idx], transl=seq.transl[idx],
            object_rotmat=seq.object_rotmat[idx], object_transl=seq.object_transl[idx],
            contact=seq.contact[idx], table_rotmat=pick(seq.table_rotmat), table_transl=pick(seq.table_transl),
            object_contact_codes=pick(seq.object_contact_codes),
        )
    t_new = np.arange(0.0, (T - 1) / seq.framerate + 1e-9, 1.0 / fps) * seq.framerate
    i0 = np.clip(np.floor(t_new).astype(int), 0, T - 1)
    i1 = np.clip(i0 + 1, 0, T - 1)
    w = torch.from_numpy(t_new - i0)
    nearest = np.where(t_new - i0 < 0.5, i0, i1)

    def lerp(a):
        if a is None:
            return None
        a = torch.from_numpy(np.asarray(a, np.float64))
        wb = w.reshape(-1, *([1] * (a.dim() - 1)))
        return ((1 - wb) * a[i0] + wb * a[i1]).numpy().astype(np.float32)

    def slerp_mats(m):
        if m is None:
            return None
        q = rot.matrix_to_quaternion(torch.from_numpy(np.asarray(m, np.float64)))
        wb = w.reshape(-1, *([1] * (q.dim() - 2)))
        return rot.quaternion_to_matrix(rot.quaternion_slerp(q[i0], q[i1], wb.expand(q[i0].shape[:-1]))).numpy()

    pose_m = rot.axis_angle_to_matrix(torch.from_numpy(seq.fullpose.astype(np.float64))).numpy()
    pose_aa = rot.matrix_to_axis_angle(torch.from_numpy(slerp_mats(pose_m))).numpy().astype(np.float32)
    return replace(
        seq, framerate=float(fps), fullpose=pose_aa, transl=lerp(seq.transl),
        object_rotmat=slerp_mats(seq.object_rotmat).astype(np.float32), object_transl=lerp(seq.object_transl),
        contact=seq.contact[nearest],
        table_rotmat=None if seq.table_rotmat is None else slerp_mats(seq.table_rotmat).astype(np.float32),
        table_transl=lerp(seq.table_transl),
        object_contact_codes=None if seq.object_contact_codes is None else seq.object_contact_codes[nearest],
    )


def build_features(seq: GrabSequence, rest_joints: torch.Tensor, centre_local=None) -> np.ndarray:
    """(T, 335) float32 features of a sequence at its own frame rate.

    ``rest_joints`` (55, 3) are the subject's (from the body model); ``centre_local`` is the
    object's bbox centre in its frame (read from the mesh when None).
    """
    if centre_local is None:
        centre_local = object_centre_local(seq.object_mesh)
    dt = torch.float64
    rotmats = rot.axis_angle_to_matrix(torch.from_numpy(seq.fullpose).to(dt))
    _, joints = sk.forward_kinematics(rotmats, rest_joints.to(dt), torch.from_numpy(seq.transl).to(dt))
    o_rot = torch.from_numpy(seq.object_rotmat).to(dt)
    o_t = torch.from_numpy(seq.object_transl).to(dt)
    centre = (o_rot @ torch.tensor(centre_local, dtype=dt)[:, None])[..., 0] + o_t
    T = seq.n_frames
    x = torch.zeros(T, FRAME_DIM, dtype=dt)
    six = rot.matrix_to_rotation_6d(rotmats[:, list(_MODELLED_JOINTS)])  # (T, 52, 6)
    cols = _ROT_COLS[:, None] + torch.arange(6)[None]
    x[:, cols.reshape(-1)] = six.reshape(T, -1)
    x[:, FIELD["root_transl"].slice] = joints[:, 0]
    x[:, FIELD["object_rot6d"].slice] = rot.matrix_to_rotation_6d(o_rot)
    x[:, FIELD["object_transl"].slice] = o_t
    x[:, FIELD["object_centre"].slice] = centre
    x[:, FIELD["lwrist_to_object"].slice] = joints[:, sk.LEFT_WRIST] - centre
    x[:, FIELD["rwrist_to_object"].slice] = joints[:, sk.RIGHT_WRIST] - centre
    x[:, FIELD["lcontact"].slice] = torch.from_numpy(seq.contact[:, :1].astype(np.float64))
    x[:, FIELD["rcontact"].slice] = torch.from_numpy(seq.contact[:, 1:].astype(np.float64))
    return x.numpy().astype(np.float32)


def features_to_rotmats(x: torch.Tensor) -> torch.Tensor:
    """(..., 335) -> (..., 55, 3, 3) local rotations; jaw and eyes are identity."""
    cols = _ROT_COLS.to(x.device)[:, None] + torch.arange(6, device=x.device)[None]
    six = x[..., cols.reshape(-1)].reshape(*x.shape[:-1], len(_MODELLED_JOINTS), 6)
    mats = rot.rotation_6d_to_matrix(six)
    eye = torch.eye(3, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], sk.NUM_JOINTS, 3, 3)
    return eye.index_copy(x.dim() - 1, torch.tensor(_MODELLED_JOINTS, device=x.device), mats)


def features_to_joints(x: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """Differentiable FK from de-normalized features: (..., T, 335) -> (..., T, 55, 3).

    ``rest_joints`` is (55, 3) or broadcastable (..., 1, 55, 3) per sample."""
    rotmats = features_to_rotmats(x)
    rest = rest_joints.to(device=x.device, dtype=x.dtype)
    pelvis = x[..., FIELD["root_transl"].slice]
    transl = pelvis - rest[..., 0, :]
    return sk.forward_kinematics(rotmats, rest, transl)[1]


def features_to_params(x: np.ndarray | torch.Tensor, rest_joints: torch.Tensor) -> dict[str, np.ndarray]:
    """Invert (T, 335) features to SMPL-X / GRAB-style parameters and object pose.

    Returns fullpose (T, 165) axis-angle, transl (T, 3) (SMPL-X convention, so
    FK(pelvis) = J_0 + transl), rotmats (T, 55, 3, 3), object_rotmat (T, 3, 3) column
    convention, object_global_orient (T, 3) in GRAB's row convention, object_transl,
    object_centre, contact (T, 2) bool.
    """
    xt = torch.as_tensor(np.asarray(x), dtype=torch.float64)
    rotmats = features_to_rotmats(xt)
    transl = xt[:, FIELD["root_transl"].slice] - rest_joints.to(torch.float64)[0]
    o_rot = rot.rotation_6d_to_matrix(xt[:, FIELD["object_rot6d"].slice])
    return {
        "rotmats": rotmats.numpy(),
        "fullpose": rot.matrix_to_axis_angle(rotmats).reshape(-1, 165).numpy(),
        "transl": transl.numpy(),
        "object_rotmat": o_rot.numpy(),
        "object_global_orient": rot.matrix_to_axis_angle(o_rot.transpose(-1, -2)).numpy(),
        "object_transl": xt[:, FIELD["object_transl"].slice].numpy(),
        "object_centre": xt[:, FIELD["object_centre"].slice].numpy(),
        "contact": (xt[:, [FIELD["lcontact"].start, FIELD["rcontact"].start]] > 0.5).numpy(),
    }
