"""Keyframe plans: the tracks a sequence is made of, and the grasp/release episodes.

A plan is a set of keyframed tracks in world coordinates, in seconds: the object pose, each
hand's wrist target (idle at the side, a free pose, or held = following the object), each
hand's finger curls, and the head's gaze weight and pitch. The torso bow/yaw and the arm
joint angles are derived per frame in `motion.py`. A hand's episode is reach -> approach ->
grip (``grasp_in``) ... release -> retract (``grasp_out``); while a hand holds, the object
moves and the hand follows it through the fixed grasp transform. `intents.py` fills plans.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..grab.format import GRAB_FPS
from ..objects.catalogue import ObjectSpec
from .grasp import Grasp
from .ik import minjerk, slerp
from .scene import SIDES, UP, Scene

FPS = GRAB_FPS
MAX_SECONDS = 12.0
IDLE, POSE, HELD = 0, 1, 2  # hand key kinds: arm hanging, a world wrist pose, following the object
_FINGERS_OPEN = np.zeros(5)
_FINGERS_PRESHAPE = np.array([0.12, 0.12, 0.12, 0.12, 0.05])
_PRECONTACT = 0.012  # the grip closes the last 12 mm while the fingers close


class PlanRejected(Exception):
    """The sampled scene cannot be realised (no grasp, out of reach, too long, the object
    would cut into the body); the generator makes another draw (the next attempt's stream)."""


def snap(t: float) -> float:
    """Key times sit on frames, so holds start and end on exact frames."""
    return round(t * FPS) / FPS


def segments(times: np.ndarray, t: np.ndarray):
    """For each time, the key at or before it, the next key and the raw fraction between."""
    k0 = np.clip(np.searchsorted(times, t + 1e-9, side="right") - 1, 0, len(times) - 1)
    k1 = np.minimum(k0 + 1, len(times) - 1)
    dt = times[k1] - times[k0]
    u = np.where(dt > 0, (t - times[k0]) / np.where(dt > 0, dt, 1.0), 0.0)
    return k0, k1, np.clip(u, 0.0, 1.0)


class Track:
    """Keyframed vectors (or rotation matrices): min-jerk between keys, constant outside."""

    def __init__(self, rotation: bool = False):
        self.rotation = rotation
        self.times: list[float] = []
        self.values: list[np.ndarray] = []

    def key(self, t: float, value) -> None:
        t = snap(t)
        if self.times and t < self.times[-1]:
            raise ValueError(f"key at {t} s before the previous one at {self.times[-1]} s")
        self.times.append(t)
        self.values.append(np.asarray(value, dtype=np.float64))

    def sample(self, t: np.ndarray) -> np.ndarray:
        k0, k1, u = segments(np.asarray(self.times), t)
        v = np.stack(self.values)
        s = minjerk(u)
        if self.rotation:
            return slerp(v[k0], v[k1], s)
        return v[k0] + s.reshape(s.shape + (1,) * (v.ndim - 1)) * (v[k1] - v[k0])


class PoseTrack:
    """Keyframed rigid poses (rotation slerp and position lerp on the same min-jerk timing)."""

    def __init__(self):
        self.rot = Track(rotation=True)
        self.pos = Track()

    def key(self, t: float, rot: np.ndarray, pos: np.ndarray) -> None:
        self.rot.key(t, rot)
        self.pos.key(t, pos)

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.rot.sample(t), self.pos.sample(t)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        r, p = self.sample(np.array([snap(t)]))
        return r[0], p[0]


@dataclass
class HandPlan:
    """Keys of one hand's wrist target and finger curls, and its grasp and hold interval."""

    side: str
    relaxed: np.ndarray  # finger curls of the hanging hand
    times: list[float] = field(default_factory=list)
    kinds: list[int] = field(default_factory=list)
    poses: list[tuple[np.ndarray, np.ndarray] | None] = field(default_factory=list)
    curls: Track = field(default_factory=Track)
    grasp: Grasp | None = None
    hold: tuple[float, float] | None = None  # [grip closed, release starts], seconds

    def key(self, t: float, kind: int, pose=None, curls=None) -> None:
        t = snap(t)
        if self.times and t < self.times[-1]:
            raise ValueError(f"{self.side} hand key at {t} s before the previous one")
        self.times.append(t)
        self.kinds.append(kind)
        self.poses.append(pose)
        self.curls.key(t, self.relaxed if curls is None else curls)


@dataclass
class Plan:
    scene: Scene
    obj: ObjectSpec
    shape_verts: np.ndarray  # object mesh vertices (object frame), for contact labels
    intent: str
    mode: str  # 'left' | 'right' | 'both' | 'left>right' | 'right>left' (pass: giver > receiver)
    object: PoseTrack
    hands: dict[str, HandPlan]
    look: Track  # gaze weight toward the object
    pitch: Track  # extra head pitch (negative tilts the head back)
    duration: float = 0.0

    @property
    def order(self) -> list[str]:
        """Holding hands by grip time: the first one carries the object while both hold."""
        return sorted((s for s in SIDES if self.hands[s].hold), key=lambda s: self.hands[s].hold[0])


def world_pose(obj_pose, grasp: Grasp) -> tuple[np.ndarray, np.ndarray]:
    """World wrist pose of a grasp on the object at ``obj_pose``."""
    r_o, p_o = obj_pose
    return r_o @ grasp.rot, p_o + r_o @ grasp.pos


def grasp_in(hp: HandPlan, t: float, grasp: Grasp, obj_pose, rng: np.random.Generator, tempo: float,
             not_before: float = 0.0) -> float:
    """Reach from the idle pose to a pre-grasp pose, approach and close the grip (the hand
    moves the last few mm while the fingers close). Keys from ``t``, durations scaled by
    ``tempo``; the approach starts no earlier than ``not_before``. Returns the time the grip
    is closed (the hold starts)."""
    r_c, p_c = world_pose(obj_pose, grasp)
    app = obj_pose[0] @ grasp.approach
    hp.key(t, IDLE)
    t = max(t + tempo * rng.uniform(0.8, 1.15), not_before)
    hp.key(t, POSE, (r_c, p_c - rng.uniform(0.06, 0.10) * app + rng.uniform(0.0, 0.04) * UP), _FINGERS_PRESHAPE)
    t += tempo * rng.uniform(0.25, 0.4)
    hp.key(t, POSE, (r_c, p_c - _PRECONTACT * app), _FINGERS_OPEN)
    t = snap(t + tempo * rng.uniform(0.2, 0.3))
    hp.key(t, HELD, curls=grasp.curls)
    hp.grasp, hp.hold = grasp, (t, t)
    return t


def grasp_out(hp: HandPlan, t: float, obj_pose, rng: np.random.Generator, tempo: float) -> float:
    """Open the grip (backing off the last few mm), retract and hang the arm, from ``t`` with
    the object at ``obj_pose``. Returns the time the arm hangs again."""
    g = hp.grasp
    r_c, p_c = world_pose(obj_pose, g)
    app = obj_pose[0] @ g.approach
    t = snap(t)
    hp.key(t, HELD, curls=g.curls)
    hp.hold = (hp.hold[0], t)
    t += tempo * rng.uniform(0.2, 0.3)
    hp.key(t, POSE, (r_c, p_c - _PRECONTACT * app), _FINGERS_OPEN)
    t += tempo * rng.uniform(0.25, 0.4)
    hp.key(t, POSE, (r_c, p_c - rng.uniform(0.06, 0.10) * app + rng.uniform(0.0, 0.04) * UP), _FINGERS_PRESHAPE)
    t += tempo * rng.uniform(0.8, 1.15)
    hp.key(t, IDLE)
    return t
