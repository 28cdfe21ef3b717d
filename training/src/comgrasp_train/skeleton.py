"""The open SMPL-X-topology skeleton: 55 joints, the SMPL-X parents, rest offsets of our own.

The rest pose lives in the SMPL-X canonical frame (y up, +z forward, the subject's left
is +x, T-pose with palms down), so GRAB's ``global_orient``/``fullpose`` drive it exactly
as they drive SMPL-X. The rest joint positions below are our own round numbers for an
adult of about 1.75 m, not values read from any SMPL-X file.

Forward kinematics follows SMPL-X's LBS joint chain: joint i's global transform is
``G_parent · [R_i | J_i - J_parent]``, the root is ``[R_0 | J_0]``, and ``transl`` is added
last, so the posed pelvis is ``R-independent J_0 + transl``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

NUM_JOINTS = 55

JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye_smplhf", "right_eye_smplhf",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2", "left_middle3",
    "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2", "left_ring3",
    "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2",
    "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1",
    "right_ring2", "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3",
)

PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)

BODY_JOINTS = tuple(range(1, 22))  # 335-D body slice: joints 1..21
LEFT_HAND_JOINTS = tuple(range(25, 40))
RIGHT_HAND_JOINTS = tuple(range(40, 55))
LEFT_WRIST, RIGHT_WRIST = 20, 21
LEFT_ANKLE, RIGHT_ANKLE, LEFT_FOOT, RIGHT_FOOT = 7, 8, 10, 11
HEAD = 15
# Distal finger joints (index3, middle3, pinky3, ring3, thumb3) per hand.
LEFT_FINGER_TIPS = (27, 30, 33, 36, 39)
RIGHT_FINGER_TIPS = (42, 45, 48, 51, 54)

# Left-body joints in canonical coordinates (metres). The right side mirrors x.
_CENTRE = {
    "pelvis": (0.0, 0.0, 0.0),
    "spine1": (0.0, 0.110, -0.025),
    "spine2": (0.0, 0.240, -0.010),
    "spine3": (0.0, 0.300, 0.010),
    "neck": (0.0, 0.510, -0.040),
    "head": (0.0, 0.580, 0.010),
    "jaw": (0.0, 0.555, 0.055),
}
_LEFT = {
    "hip": (0.070, -0.090, -0.005),
    "knee": (0.105, -0.460, 0.000),
    "ankle": (0.090, -0.860, -0.040),
    "foot": (0.115, -0.915, 0.080),
    "collar": (0.080, 0.415, -0.030),
    "shoulder": (0.185, 0.455, -0.045),
    "elbow": (0.445, 0.440, -0.070),
    "wrist": (0.705, 0.445, -0.065),
    "eye_smplhf": (0.032, 0.640, 0.085),
}
# Finger joints relative to the left wrist (palm down, fingers along +x).
_LEFT_FINGERS = {
    "index": ((0.090, -0.006, 0.026), (0.036, -0.002, 0.002), (0.024, -0.002, 0.000)),
    "middle": ((0.095, -0.004, 0.004), (0.040, -0.002, 0.000), (0.027, -0.002, 0.000)),
    "pinky": ((0.078, -0.010, -0.038), (0.026, -0.002, -0.004), (0.018, -0.002, -0.002)),
    "ring": ((0.088, -0.007, -0.018), (0.036, -0.002, -0.002), (0.025, -0.002, -0.001)),
    "thumb": ((0.030, -0.018, 0.030), (0.028, -0.008, 0.022), (0.024, -0.004, 0.016)),
}
# Length of the distal segment beyond the last joint (to the finger tip), metres.
FINGER_TIP_LENGTH = {"index": 0.022, "middle": 0.024, "pinky": 0.018, "ring": 0.022, "thumb": 0.022}
FINGERS = ("index", "middle", "pinky", "ring", "thumb")


def _build_default_rest() -> np.ndarray:
    rest = np.zeros((NUM_JOINTS, 3))
    idx = {n: i for i, n in enumerate(JOINT_NAMES)}
    for name, p in _CENTRE.items():
        rest[idx[name]] = p
    for side, sx in (("left", 1.0), ("right", -1.0)):
        for name, p in _LEFT.items():
            rest[idx[f"{side}_{name}"]] = (sx * p[0], p[1], p[2])
        wrist = rest[idx[f"{side}_wrist"]]
        for finger, segs in _LEFT_FINGERS.items():
            pos = wrist.copy()
            for k, off in enumerate(segs, start=1):
                pos = pos + np.array((sx * off[0], off[1], off[2]))
                rest[idx[f"{side}_{finger}{k}"]] = pos
    # Place the pelvis at the height SMPL-X puts it relative to the template origin.
    rest[:, 1] -= 0.35
    return rest


DEFAULT_REST_JOINTS: np.ndarray = _build_default_rest()


@dataclass(frozen=True)
class Proportions:
    """Body-proportion factors of a subject, applied to the default rest offsets."""

    height: float = 1.0  # overall scale
    arm: float = 1.0  # shoulder->wrist bones
    leg: float = 1.0  # hip->ankle bones
    shoulder_width: float = 1.0  # collar/shoulder lateral offsets
    hip_width: float = 1.0
    hand: float = 1.0  # all finger bones and the palm
    torso: float = 1.0  # spine chain and neck


def _bone_factor(j: int, p: Proportions) -> np.ndarray:
    name = JOINT_NAMES[j]
    f = np.ones(3)
    if name.endswith(("knee", "ankle")):
        f *= p.leg
    elif name.endswith("hip"):
        f[0] *= p.hip_width
    elif name.endswith(("elbow", "wrist")):
        f *= p.arm
    elif name.endswith(("collar", "shoulder")):
        f[0] *= p.shoulder_width
        f[1:] *= p.torso
    elif any(fn in name for fn in FINGERS):
        f *= p.hand
    elif name.startswith(("spine", "neck", "head")):
        f *= p.torso
    return f * p.height


def scaled_rest_joints(p: Proportions, base: np.ndarray | None = None) -> np.ndarray:
    """Rest joints with every bone offset scaled by its proportion factor."""
    base = DEFAULT_REST_JOINTS if base is None else base
    out = np.zeros_like(base)
    out[0] = base[0] * p.height
    for j in range(1, NUM_JOINTS):
        par = PARENTS[j]
        out[j] = out[par] + (base[j] - base[par]) * _bone_factor(j, p)
    return out


def _depth_levels(parents: tuple[int, ...]) -> list[torch.Tensor]:
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return [
        torch.tensor([j for j in range(len(parents)) if depth[j] == d])
        for d in range(1, max(depth) + 1)
    ]


_LEVELS = _depth_levels(PARENTS)
_PARENTS_T = torch.tensor(PARENTS)


def _fk_plan(parents: tuple[int, ...], levels: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """The joints in level order (root first, then each depth level); for each level, the
    position of each of its joints' parent within the level above; and the permutation
    that puts level order back in joint order."""
    order = [0] + [int(j) for lvl in levels for j in lvl]
    prev, where = [0], []
    for lvl in levels:
        where.append(torch.tensor([prev.index(parents[int(j)]) for j in lvl]))
        prev = [int(j) for j in lvl]
    return torch.tensor(order), where, torch.tensor(order).argsort()


_LEVEL_ORDER, _PARENT_IN_LEVEL, _JOINT_ORDER = _fk_plan(PARENTS, _LEVELS)
_LEVEL_SIZES = [1] + [len(lvl) for lvl in _LEVELS]
_DEVICE_INDEX: dict[torch.device, tuple] = {}


def _index_tensors(device: torch.device) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """The parent and FK-plan index tensors on ``device`` (made once per device)."""
    if device not in _DEVICE_INDEX:
        _DEVICE_INDEX[device] = (_PARENTS_T.to(device), _LEVEL_ORDER.to(device),
                                 [w.to(device) for w in _PARENT_IN_LEVEL], _JOINT_ORDER.to(device))
    return _DEVICE_INDEX[device]


def forward_kinematics(
    rotmats: torch.Tensor, rest_joints: torch.Tensor, transl: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched FK on the 55-joint tree.

    rotmats: (..., 55, 3, 3) local rotations; rest_joints: (..., 55, 3) broadcastable;
    transl: (..., 3) or None. Returns global rotations (..., 55, 3, 3) and world joint
    positions (..., 55, 3). One tree depth at a time (about 15 steps), each on that
    level's joints only (every parent is in the level above): the inputs are put in level
    order once and split into views, and the outputs permuted back once, so the work is
    linear in the joints, with no per-level copy of the whole pose (which made FK about
    half of a VQ training step on the CPU).
    """
    rest_joints = rest_joints.to(device=rotmats.device, dtype=rotmats.dtype)
    batch = rotmats.shape[:-3]
    rest_joints = rest_joints.expand(*batch, NUM_JOINTS, 3)
    parents_t, level_order, parent_in_level, order = _index_tensors(rotmats.device)
    jdim = rotmats.dim() - 3
    offsets = rest_joints - rest_joints[..., parents_t.clamp_min(0), :]
    local = rotmats.index_select(jdim, level_order).split(_LEVEL_SIZES, jdim)
    off = offsets.index_select(jdim, level_order).split(_LEVEL_SIZES, jdim)
    g_rot, g_pos = [local[0]], [rest_joints[..., :1, :]]
    for k, where in enumerate(parent_in_level, start=1):
        pr = g_rot[-1].index_select(jdim, where)
        pp = g_pos[-1].index_select(jdim, where)
        g_rot.append(pr @ local[k])
        g_pos.append(pp + (pr @ off[k][..., None])[..., 0])
    g_rot = torch.cat(g_rot, jdim).index_select(jdim, order)
    g_pos = torch.cat(g_pos, jdim).index_select(jdim, order)
    if transl is not None:
        g_pos = g_pos + transl[..., None, :].to(g_pos.dtype)
    return g_rot, g_pos


def global_to_local(global_rot: torch.Tensor) -> torch.Tensor:
    """Inverse of the rotation part of FK: local_i = G_parent^T G_i."""
    par = _index_tensors(global_rot.device)[0].clamp_min(0)
    parent_rot = global_rot[..., par, :, :]
    local = parent_rot.transpose(-1, -2) @ global_rot
    local[..., 0, :, :] = global_rot[..., 0, :, :]
    return local
