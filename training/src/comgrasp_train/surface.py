"""Open surface proxies: capsules on the open skeleton, sampled into points.

Each capsule is rigidly attached to one joint (the bone from a joint to its child moves
with that joint's global transform), so posing the proxy is a rigid transform per point.
Every point carries a GRAB contact part code (joint index + 1; palm capsules use the
wrist's code 21/22), so SynthGrasp's ``contact/body`` uses GRAB's code semantics.

The proxy stands in for SMPL-X vertices in MPVPE, collision and contact measures when the
user has no SMPL-X model. Hands are sampled densely (about 4 mm), the rest coarsely.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from . import skeleton as sk


@dataclass(frozen=True)
class Capsule:
    a: np.ndarray
    b: np.ndarray
    radius: float
    joint: int  # the joint whose transform moves it
    code: int  # GRAB contact code (joint + 1)


@dataclass(frozen=True)
class SurfaceProxy:
    joint: np.ndarray  # (P,) attachment joint per point
    rest_points: np.ndarray  # (P, 3) in the rest pose
    code: np.ndarray  # (P,) GRAB contact part code
    capsules: tuple[Capsule, ...]

    @property
    def num_points(self) -> int:
        return int(self.joint.shape[0])

    def mask(self, codes) -> np.ndarray:
        return np.isin(self.code, np.asarray(list(codes)))


LEFT_HAND_CODES = (21, *range(26, 41))
RIGHT_HAND_CODES = (22, *range(41, 56))
FOOT_CODES = (8, 9, 11, 12)


def _capsules(rest: np.ndarray) -> list[Capsule]:
    idx = {n: i for i, n in enumerate(sk.JOINT_NAMES)}
    J = rest
    caps: list[Capsule] = []

    def add(a, b, r, joint, code=None):
        caps.append(Capsule(np.asarray(a, float), np.asarray(b, float), r, joint, joint + 1 if code is None else code))

    def bone(parent: str, child: str, r: float):
        add(J[idx[parent]], J[idx[child]], r, idx[parent])

    up = np.array([0.0, 1.0, 0.0])
    fwd = np.array([0.0, 0.0, 1.0])
    add(J[idx["left_hip"]], J[idx["right_hip"]], 0.085, 0)
    bone("pelvis", "spine1", 0.10)
    bone("spine1", "spine2", 0.10)
    bone("spine2", "spine3", 0.11)
    add(J[idx["left_collar"]] - 0.06 * up, J[idx["right_collar"]] - 0.06 * up, 0.08, idx["spine3"])
    bone("neck", "head", 0.05)
    head = J[idx["head"]]
    add(head + 0.05 * up + 0.02 * fwd, head + 0.10 * up + 0.02 * fwd, 0.09, idx["head"])
    for s in ("left", "right"):
        bone(f"{s}_hip", f"{s}_knee", 0.065)
        bone(f"{s}_knee", f"{s}_ankle", 0.045)
        bone(f"{s}_ankle", f"{s}_foot", 0.035)
        foot = J[idx[f"{s}_foot"]]
        add(foot, foot + 0.06 * fwd, 0.03, idx[f"{s}_foot"])
        bone(f"{s}_collar", f"{s}_shoulder", 0.05)
        bone(f"{s}_shoulder", f"{s}_elbow", 0.042)
        bone(f"{s}_elbow", f"{s}_wrist", 0.033)
        wrist = idx[f"{s}_wrist"]
        for f in ("index", "middle", "ring", "pinky"):
            add(J[wrist], J[idx[f"{s}_{f}1"]], 0.012, wrist)
        add(J[wrist], J[idx[f"{s}_thumb1"]], 0.014, wrist)
        for f in sk.FINGERS:
            j1, j2, j3 = (idx[f"{s}_{f}{k}"] for k in (1, 2, 3))
            add(J[j1], J[j2], 0.0095 if f == "thumb" else 0.0088, j1)
            add(J[j2], J[j3], 0.0088 if f == "thumb" else 0.0082, j2)
            d = J[j3] - J[j2]
            tip = J[j3] + sk.FINGER_TIP_LENGTH[f] * d / np.linalg.norm(d)
            add(J[j3], tip, 0.0078 if f == "thumb" else 0.0075, j3)
    return caps


def _sample_capsule(c: Capsule, spacing: float) -> np.ndarray:
    axis = c.b - c.a
    length = float(np.linalg.norm(axis))
    u = axis / max(length, 1e-9)
    tmp = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    v = np.cross(u, tmp)
    v /= np.linalg.norm(v)
    w = np.cross(u, v)
    n_around = max(8, int(np.ceil(2 * np.pi * c.radius / spacing)))
    n_along = max(2, int(np.ceil(length / spacing)) + 1)
    phi = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = np.cos(phi)[:, None] * v + np.sin(phi)[:, None] * w
    pts = [c.a + t * axis + c.radius * ring for t in np.linspace(0, 1, n_along)]
    # Hemispherical caps: a few latitude rings plus the pole.
    n_lat = max(2, int(np.ceil(0.5 * np.pi * c.radius / spacing)))
    for end, sgn in ((c.a, -1.0), (c.b, 1.0)):
        for th in np.linspace(0, np.pi / 2, n_lat + 1)[1:-1]:
            pts.append(end + c.radius * (np.cos(th) * ring + sgn * np.sin(th) * u))
        pts.append((end + sgn * c.radius * u)[None])
    return np.concatenate(pts, 0)


def build_proxy(rest_joints: np.ndarray, hand_spacing: float = 0.004, body_spacing: float = 0.02) -> SurfaceProxy:
    """Sample the capsule proxy of a skeleton given its rest joints (55, 3)."""
    caps = _capsules(np.asarray(rest_joints, dtype=np.float64))
    hand_codes = set(LEFT_HAND_CODES) | set(RIGHT_HAND_CODES)
    joints, points, codes = [], [], []
    for c in caps:
        p = _sample_capsule(c, hand_spacing if c.code in hand_codes else body_spacing)
        points.append(p)
        joints.append(np.full(len(p), c.joint))
        codes.append(np.full(len(p), c.code))
    return SurfaceProxy(np.concatenate(joints), np.concatenate(points), np.concatenate(codes), tuple(caps))


def pose_points(
    proxy_joint: torch.Tensor, proxy_rest: torch.Tensor, rest_joints: torch.Tensor,
    global_rot: torch.Tensor, joints: torch.Tensor,
) -> torch.Tensor:
    """Posed proxy points (..., P, 3) from FK output: p = G_j (p_rest - J_rest_j) + J_j."""
    proxy_joint = proxy_joint.to(joints.device)
    local = proxy_rest.to(joints) - rest_joints.to(joints)[..., proxy_joint, :]
    rot = global_rot[..., proxy_joint, :, :]
    return (rot @ local[..., None])[..., 0] + joints[..., proxy_joint, :]
