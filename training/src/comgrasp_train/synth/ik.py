"""Kinematics for the SynthGrasp generator, vectorized over frames with numpy.

* min-jerk timing and rotation helpers (scipy does the axis-angle conversions);
* the torso chain in closed form as a function of a forward bow and a yaw, so the bow that
  brings a target within reach can be searched over a grid for every frame at once;
* analytic two-bone arm IK with a pole vector, exact whenever the target is within reach;
* head look-at.

All rotations follow the skeleton's FK (`skeleton.py`): a local rotation acts in the
rest-aligned frame, ``G_child = G_parent @ L_child``, and the rest pose has every global
rotation equal to the identity (canonical frame); the upright world pose of the pelvis is
``subjects.ROOT_ROT``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .. import skeleton as sk

SPINE = (3, 6, 9)  # spine1..3: each gets the same local rotation
NECK, HEAD, SPINE3 = 12, 15, 9
LEFT_HIP, RIGHT_HIP = 1, 2


def minjerk(u: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile 10u^3 - 15u^4 + 6u^5 on u clipped to [0, 1]."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)


def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    rv = np.asarray(rv, dtype=np.float64)
    return Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix().reshape(*rv.shape[:-1], 3, 3)


def matrix_to_rotvec(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(*m.shape[:-2], 3)


def axis_angle(axis, angle) -> np.ndarray:
    """Rotation matrices about a (broadcast) axis by a (broadcast) angle."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return rotvec_to_matrix(axis * np.asarray(angle, dtype=np.float64)[..., None])


def slerp(r0: np.ndarray, r1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Geodesic interpolation r0 -> r1 at fraction s (broadcast over leading dims)."""
    rel = matrix_to_rotvec(np.swapaxes(r0, -1, -2) @ r1)
    return r0 @ rotvec_to_matrix(rel * np.asarray(s)[..., None])


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Orthonormal frame (columns a, b orthogonalized against a, a x b)."""
    a = unit(a)
    b = unit(b - (a * b).sum(-1, keepdims=True) * a)
    return np.stack([a, b, np.cross(a, b)], axis=-1)


def align(a0, b0, a, b) -> np.ndarray:
    """The rotation that takes direction a0 to a exactly and b0 as close to b as it can."""
    return frame(a, b) @ np.swapaxes(frame(a0, b0), -1, -2)


def canonical_rot(yaw, pitch) -> np.ndarray:
    """Ry(yaw) @ Rx(pitch) in the canonical frame (yaw about the up axis, pitch forward/down)."""
    yaw, pitch = np.broadcast_arrays(np.asarray(yaw, float), np.asarray(pitch, float))
    return axis_angle([0.0, 1.0, 0.0], yaw) @ axis_angle([1.0, 0.0, 0.0], pitch)


# ---- torso --------------------------------------------------------------------------------


@dataclass
class Torso:
    """World pose of the upper body for a forward bow ``theta`` and a yaw ``psi`` (to the
    left). ``hip_share`` of the bow is a hinge of the pelvis about the line through both hip
    joints (the legs counter-rotate, so hips, knees and feet stay exactly in place); the rest
    and the yaw are shared equally by spine1..3."""

    pelvis_rot: np.ndarray  # (..., 3, 3) pelvis global rotation
    pelvis_pos: np.ndarray  # (..., 3) pelvis position
    hip_local: np.ndarray  # (..., 3, 3) local rotation of both hips (undoes the hinge)
    local: np.ndarray  # (..., 3, 3) local rotation of each spine joint
    rot3: np.ndarray  # (..., 3, 3) global rotation of spine3 (= collars, which stay at rest)
    pos3: np.ndarray  # (..., 3) spine3 position

    def point(self, rest: np.ndarray, j: int) -> np.ndarray:
        """World position of a joint rigidly attached to spine3 (collars, shoulders, neck)."""
        return self.pos3 + (self.rot3 @ (rest[j] - rest[SPINE3]))


def torso(rest: np.ndarray, root_rot: np.ndarray, pelvis: np.ndarray, theta, psi, hip_share: float) -> Torso:
    """``pelvis`` is the world pelvis position of the upright pose."""
    theta, psi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(psi, float))
    hinge = axis_angle([1.0, 0.0, 0.0], hip_share * theta)
    hips = 0.5 * (rest[LEFT_HIP] + rest[RIGHT_HIP]) - rest[0]
    pelvis_pos = pelvis + (hips - hinge @ hips) @ root_rot.T
    local = canonical_rot(psi / 3.0, (1.0 - hip_share) * theta / 3.0)
    g = root_rot @ hinge
    pelvis_rot = g
    pos = pelvis_pos + g @ (rest[SPINE[0]] - rest[0])
    for child, parent in ((SPINE[1], SPINE[0]), (SPINE[2], SPINE[1])):
        g = g @ local
        pos = pos + g @ (rest[child] - rest[parent])
    return Torso(pelvis_rot, pelvis_pos, np.swapaxes(hinge, -1, -2), local, g @ local, pos)


# ---- arms ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Arm:
    """Rest geometry of one arm. The elbow hinge is the rest upper arm x forward, so a
    hanging arm flexes its forearm forward with the palm facing the thigh."""

    collar: int
    shoulder: int
    elbow: int
    wrist: int
    upper: float  # shoulder -> elbow length
    fore: float  # elbow -> wrist length
    u0: np.ndarray  # rest upper-arm direction
    v0: np.ndarray  # rest bend direction (forward, orthogonal to u0)
    f0: np.ndarray  # rest forearm direction
    h0: np.ndarray  # rest hinge axis u0 x v0

    @property
    def reach(self) -> float:
        return self.upper + self.fore


def make_arm(rest: np.ndarray, side: str) -> Arm:
    c, s, e, w = (sk.JOINT_NAMES.index(f"{side}_{n}") for n in ("collar", "shoulder", "elbow", "wrist"))
    up, fo = rest[e] - rest[s], rest[w] - rest[e]
    u0 = unit(up)
    fwd = np.array([0.0, 0.0, 1.0])
    v0 = unit(fwd - (fwd @ u0) * u0)
    return Arm(c, s, e, w, float(np.linalg.norm(up)), float(np.linalg.norm(fo)), u0, v0, unit(fo),
               unit(np.cross(u0, v0)))


def arm_ik(arm: Arm, shoulder: np.ndarray, parent_rot: np.ndarray, target_pos: np.ndarray,
           target_rot: np.ndarray, pole: np.ndarray, swivel: float = 1.2, twist_share: float = 0.5):
    """Two-bone IK: local rotations (shoulder, elbow, wrist) that put the wrist at
    ``target_pos`` with global rotation ``target_rot``.

    The elbow goes toward ``pole``, swivelled about the shoulder-wrist line (by up to
    ``swivel`` rad, smoothly) toward where the forearm would line up with the hand, which
    keeps the wrist from bending far. Half (``twist_share``) of the wrist's twist about the
    forearm moves into the elbow, the way forearm pronation is shared in SMPL-X. Returns the
    three (..., 3, 3) locals and the reach shortfall (m), 0 when the target is reachable.
    """
    a, b = arm.upper, arm.fore
    d_vec = target_pos - shoulder
    d = np.linalg.norm(d_vec, axis=-1)
    u_t = d_vec / np.maximum(d, 1e-9)[..., None]
    dc = np.clip(d, abs(a - b) + 1e-6, (a + b) * (1.0 - 1e-9))
    x = (a * a - b * b + dc * dc) / (2.0 * dc)
    h = np.sqrt(np.maximum(a * a - x * x, 0.0))
    p_perp = unit(pole - (pole * u_t).sum(-1, keepdims=True) * u_t)
    # The elbow direction that aligns the forearm with the hand is away from the hand's axis.
    along = target_rot @ arm.f0
    best = -(along - (along * u_t).sum(-1, keepdims=True) * u_t)
    turn = swivel * (np.cross(p_perp, best) * u_t).sum(-1)  # |best| sin(angle): smooth, fades out
    p_perp = unit(p_perp * np.cos(turn)[..., None] + np.cross(u_t, p_perp) * np.sin(turn)[..., None])
    elbow = shoulder + x[..., None] * u_t + h[..., None] * p_perp
    wrist = shoulder + dc[..., None] * u_t
    u = (elbow - shoulder) / a
    f = (wrist - elbow) / b
    g_sh = align(arm.u0, arm.v0, u, -p_perp)
    hinge = unit(np.cross(u, -p_perp))
    g_el = align(arm.f0, arm.h0, f, hinge)
    l_wr = np.swapaxes(g_el, -1, -2) @ target_rot
    q = Rotation.from_matrix(l_wr.reshape(-1, 3, 3)).as_quat().reshape(*l_wr.shape[:-2], 4)
    twist = 2.0 * np.arctan2(q[..., :3] @ arm.f0, q[..., 3])
    twist = (twist + np.pi) % (2 * np.pi) - np.pi
    share = axis_angle(arm.f0, twist_share * twist)
    g_el = g_el @ share
    l_wr = np.swapaxes(share, -1, -2) @ l_wr
    l_sh = np.swapaxes(parent_rot, -1, -2) @ g_sh
    l_el = np.swapaxes(g_sh, -1, -2) @ g_el
    return l_sh, l_el, l_wr, np.abs(d - dc)


# ---- head ---------------------------------------------------------------------------------


def look_at(rest: np.ndarray, tor: Torso, target: np.ndarray, weight: np.ndarray, pitch_offset: np.ndarray,
            yaw_limit: float = 1.0, pitch_limits: tuple[float, float] = (-0.6, 0.8)) -> np.ndarray:
    """Neck and head local rotation (each gets half) that turn the face toward ``target`` by
    ``weight``, plus ``pitch_offset`` (positive looks down). Returns (..., 3, 3)."""
    d = np.einsum("...ji,...j->...i", tor.rot3, target - tor.point(rest, NECK))
    yaw = np.clip(weight * np.arctan2(d[..., 0], d[..., 2]), -yaw_limit, yaw_limit)
    pitch = np.clip(weight * np.arctan2(-d[..., 1], np.hypot(d[..., 0], d[..., 2])) + pitch_offset,
                    *pitch_limits)
    return canonical_rot(yaw / 2.0, pitch / 2.0)


def head_pose(rest: np.ndarray, tor: Torso, neck_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Global rotation and position of the head when neck and head both get ``neck_local``."""
    g_neck = tor.rot3 @ neck_local
    pos = tor.point(rest, NECK) + g_neck @ (rest[HEAD] - rest[NECK])
    return g_neck @ neck_local, pos
