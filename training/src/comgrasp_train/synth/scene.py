"""The scene of one sequence: a subject standing at a table, with its per-sequence style.

The subject faces +y with the pelvis at a random spot near the origin; the table (height
0.70-0.90 m) stands in front. The style (idle arm pose, elbow pole, relaxed fingers,
resting bow, how much the torso turns and how much of a bow the hips take) is drawn per
sequence. ``required_bend`` is how far the torso must bow for a hand to reach a point.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from .. import skeleton as sk
from ..objects.catalogue import TABLE_SIZE, ObjectSpec
from .grasp import Hand
from .ik import Arm, Torso, axis_angle, head_pose, make_arm, torso, unit
from .subjects import ROOT_ROT, SubjectModel, subject_model

THETA_MAX = np.radians(95.0)  # deepest forward bow (hip hinge + spine)
REACH_LIMIT = 0.96  # fraction of the arm length a target may be from the shoulder
SIDES = ("left", "right")
UP = np.array([0.0, 0.0, 1.0])


def side_sign(side: str) -> float:
    """World x sign of a body side (the subject faces +y, its left is world -x)."""
    return -1.0 if side == "left" else 1.0


@cache
def hand_model(sbj_id: str, side: str) -> Hand:
    return Hand(subject_model(sbj_id), side)


@dataclass
class Scene:
    """A subject at a table, with the per-sequence style of its idle arms, poles and torso."""

    model: SubjectModel
    pelvis: np.ndarray  # world pelvis position when upright
    table_height: float
    table_centre: np.ndarray  # world centre of the table's top surface
    hands: dict[str, Hand]
    arms: dict[str, Arm]
    pole: dict[str, np.ndarray]  # elbow pole direction in the spine3 frame (canonical)
    idle: dict[str, tuple[np.ndarray, np.ndarray]]  # hanging wrist rotation and offset from the shoulder (canonical)
    idle_front: dict[str, float]  # how far the hanging hand reaches forward of its wrist
    relaxed: dict[str, np.ndarray]
    theta0: float  # resting forward bow
    psi_gain: float  # how much the torso turns toward the object
    hip_share: float  # share of the bow taken by the hips

    @property
    def rest(self) -> np.ndarray:
        return self.model.rest

    @property
    def near_edge(self) -> float:
        return float(self.table_centre[1] - TABLE_SIZE[1] / 2)

    def torso(self, theta, psi) -> Torso:
        return torso(self.rest, ROOT_ROT, self.pelvis, theta, psi, self.hip_share)

    def psi_toward(self, p: np.ndarray) -> float:
        """Torso yaw toward a point; none for points near the midline (e.g. the mouth)."""
        x = p[0] - self.pelvis[0]
        x = np.sign(x) * max(abs(x) - 0.08, 0.0)
        return float(np.clip(self.psi_gain * np.arctan2(-x, max(p[1] - self.pelvis[1], 0.15)), -0.35, 0.35))

    def required_bend(self, side: str, target: np.ndarray, psi: np.ndarray) -> np.ndarray:
        """Smallest forward bow (per frame) that brings ``target`` within reach of the arm,
        THETA_MAX where none does; linear between grid values."""
        grid = np.linspace(0.0, THETA_MAX, 20)
        arm = self.arms[side]
        shoulder = self.torso(grid[:, None], np.asarray(psi)[None, :]).point(self.rest, arm.shoulder)
        excess = np.linalg.norm(target[None] - shoulder, axis=-1) - REACH_LIMIT * arm.reach  # (G, T)
        ok = excess <= 0
        k = np.where(ok.any(axis=0), ok.argmax(axis=0), len(grid))
        cols = np.arange(excess.shape[1])
        kk = np.clip(k, 1, len(grid) - 1)
        e0, e1 = excess[kk - 1, cols], excess[kk, cols]
        interp = grid[kk - 1] + (grid[kk] - grid[kk - 1]) * e0 / np.maximum(e0 - e1, 1e-12)
        return np.where(k == 0, 0.0, np.where(k >= len(grid), THETA_MAX, interp))

    def idle_pose(self, side: str, tor: Torso, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The free arm hangs from its shoulder with gravity, turned with the torso's yaw but
        not its bow; the hand stays 2 cm behind the table edge (smooth limits), so a deep bow
        swings it neither backward nor under the table."""
        rot, offset = self.idle[side]
        heading = axis_angle(UP, psi) @ ROOT_ROT
        shoulder = tor.point(self.rest, self.arms[side].shoulder)
        pos = shoulder + heading @ offset
        k = 0.02  # smoothness of the limits (m)
        limit = self.near_edge - self.idle_front[side] - 0.02
        pos[..., 1] -= k * np.logaddexp(0.0, (pos[..., 1] - limit) / k)
        # Pulled back, the hand rises as far as needed to stay within reach.
        reach2 = (0.95 * self.arms[side].reach) ** 2 - ((pos - shoulder)[..., :2] ** 2).sum(-1)
        low = shoulder[..., 2] - np.sqrt(np.maximum(reach2, 0.0))
        pos[..., 2] += k * np.logaddexp(0.0, (low - pos[..., 2]) / k)
        return heading @ rot, pos

    def mouth(self, pitch: float) -> np.ndarray:
        """World mouth position with the torso at rest and the head pitched by ``pitch``."""
        tor = self.torso(self.theta0, 0.0)
        neck_local = axis_angle([1.0, 0.0, 0.0], pitch / 2.0)
        g_head, head = head_pose(self.rest, tor, neck_local)
        scale = np.linalg.norm(self.rest[15] - self.rest[12]) / np.linalg.norm(
            sk.DEFAULT_REST_JOINTS[15] - sk.DEFAULT_REST_JOINTS[12])
        return head + g_head @ (np.array([0.0, -0.03, 0.085]) * scale)

    def on_table(self, obj: ObjectSpec, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """Pose of the object resting upright on the table at world (x, y)."""
        return axis_angle(UP, yaw), np.array([x, y, self.table_height + obj.half_height])


def make_scene(model: SubjectModel, rng: np.random.Generator) -> Scene:
    pelvis = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), model.pelvis_height])
    table_height = rng.uniform(0.70, 0.90)
    centre = pelvis + np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.2, 0.28) + TABLE_SIZE[1] / 2, 0.0])
    centre[2] = table_height
    rest = model.rest
    arms = {s: make_arm(rest, s) for s in SIDES}
    rot = np.tile(np.eye(3), (1, sk.NUM_JOINTS, 1, 1))
    pole, relaxed = {}, {}
    for s in SIDES:
        sign = 1.0 if s == "left" else -1.0  # canonical x of the side
        rot[0, arms[s].shoulder] = axis_angle([0.0, 0.0, 1.0], -sign * np.radians(rng.uniform(70, 82)))
        rot[0, arms[s].elbow] = axis_angle(arms[s].h0, np.radians(rng.uniform(8, 20)))
        pole[s] = unit(np.array([sign * rng.uniform(0.5, 0.9), -rng.uniform(0.3, 0.6), -1.0]))
        relaxed[s] = np.concatenate([rng.uniform(0.15, 0.35, 4), rng.uniform(0.05, 0.2, 1)])
    g, j = (x[0].numpy() for x in sk.forward_kinematics(torch.from_numpy(rot), torch.from_numpy(rest)))
    idle = {s: (g[arms[s].wrist], j[arms[s].wrist] - j[arms[s].shoulder]) for s in SIDES}
    hands = {s: hand_model(model.spec.sbj_id, s) for s in SIDES}
    front = {s: float((hands[s].points(relaxed[s])[0] @ idle[s][0].T)[:, 2].max()) for s in SIDES}
    return Scene(model, pelvis, table_height, centre, hands, arms, pole, idle, front, relaxed,
                 rng.uniform(0.0, 0.06), rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.6))
