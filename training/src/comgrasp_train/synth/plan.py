"""Keyframe plans of the SynthGrasp intents.

A plan is a set of keyframed tracks in world coordinates, in seconds: the object pose, each
hand's wrist target (idle at the side, a free pose, or held = following the object), each
hand's finger curls, and the head's gaze weight and pitch. The torso bend/yaw and the arm
joint angles are derived per frame in `motion.py`. Every intent is approach -> grip ->
manipulate -> release -> retract with randomized timing; while a hand holds, the object
moves and the hand follows it through the fixed grasp transform.

Intents (GRAB's motion_intent names): lift, pass (one hand hands over to the other, which
puts it down), offhand (held out forward at arm's length, as when offering it), inspect
(brought before the face and turned), drink (to the mouth, tilted), pour (tilted over a
spot on the table).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import torch

from .. import skeleton as sk
from ..grab.format import GRAB_FPS
from ..objects.catalogue import TABLE_SIZE, ObjectSpec
from .grasp import Grasp, Hand, Obstacles, edge_point, make_grasp, floor_plane
from .ik import Arm, Torso, axis_angle, head_pose, make_arm, minjerk, slerp, torso, unit
from .subjects import ROOT_ROT, SubjectModel, subject_model

FPS = GRAB_FPS
MAX_SECONDS = 12.0
THETA_MAX = np.radians(95.0)  # deepest forward bow (hip hinge + spine)
REACH_LIMIT = 0.96  # fraction of the arm length a target may be from the shoulder
IDLE, POSE, HELD = 0, 1, 2  # hand key kinds: arm hanging, a world wrist pose, following the object
SIDES = ("left", "right")
UP = np.array([0.0, 0.0, 1.0])
_BOXY = ("box", "pyramid")  # shapes with faces: side/top grasps are aligned to a face
_FINGERS_OPEN = np.zeros(5)
_FINGERS_PRESHAPE = np.array([0.12, 0.12, 0.12, 0.12, 0.05])
_PRECONTACT = 0.012  # the grip closes the last 12 mm while the fingers close


class PlanRejected(Exception):
    """The sampled scene cannot be realised (no grasp, out of reach, too long); the
    generator draws another one from the same random stream."""


def snap(t: float) -> float:
    """Key times sit on frames, so holds start and end on exact frames."""
    return round(t * FPS) / FPS


def side_sign(side: str) -> float:
    """World x sign of a body side (the subject faces +y, its left is world -x)."""
    return -1.0 if side == "left" else 1.0


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

    @property
    def last(self) -> np.ndarray:
        return self.values[-1]


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


@lru_cache(maxsize=None)
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


# ---- grasps -------------------------------------------------------------------------------


def _boxy(obj: ObjectSpec) -> bool:
    return any(p.kind in _BOXY for p in obj.shape.parts)


def _snap_to_faces(direction: np.ndarray, obj_rot: np.ndarray) -> np.ndarray:
    """The object's horizontal face normal closest to a horizontal direction."""
    axes = np.concatenate([obj_rot[:, :2].T, -obj_rot[:, :2].T])
    return axes[np.argmax(axes @ direction)]


def _turn(v: np.ndarray, angle: float) -> np.ndarray:
    return axis_angle(UP, angle) @ v


def try_grasp(scene: Scene, side: str, obj: ObjectSpec, verts: np.ndarray, pose, style: str,
              direction: np.ndarray, rng: np.random.Generator, obstacles: Obstacles, floor: float,
              handle: bool) -> Grasp | None:
    """One grasp attempt on the upright object at ``pose``. ``style`` 'side': the palm on the
    side facing ``direction`` (horizontal, from the object toward the palm), at the handle if
    ``handle``; 'top': the palm on top, fingers along ``direction``. The hand stays
    above the world height ``floor`` (the table top, or for a hand-over the object's bottom,
    so that the receiving hand can put it down); ``obstacles`` must include that plane."""
    hand = scene.hands[side]
    r_o, p_o = pose
    hz = obj.half_height
    if style == "side":
        if handle:
            target = np.asarray(obj.handle, float)
            direction = r_o @ unit(target * np.array([1.0, 1.0, 0.0]))
        else:
            if _boxy(obj):
                direction = _snap_to_faces(direction, r_o)
            target = np.array([0.0, 0.0, rng.uniform(-0.35, 0.25) * hz])
        normal = -direction
        lam = 0.5
        # Thumb up, then rolled about the palm normal toward continuing the line from the
        # shoulder (so the wrist need not bend sideways), as far as the floor lets the hand.
        upright = hand.orientation(normal, UP)
        shoulder = scene.torso(scene.theta0, 0.0).point(scene.rest, scene.arms[side].shoulder)
        reach = p_o + r_o @ target - shoulder
        reach -= (reach @ normal) * normal
        fingers = upright @ hand.canonical[:, 0]
        roll = np.arctan2(np.cross(fingers, reach) @ normal, fingers @ reach)
        jitter = rng.uniform(-0.2, 0.2)
        highest = obj.handle[2] + 0.02 if handle else hz + 0.01  # a low object: the hand's lower half
        for share in (0.6, 0.3, 0.0):
            rot_w = axis_angle(normal, share * roll + jitter) @ upright
            low = ((hand.open_points - hand.anchor(lam)) @ rot_w.T)[:, 2].min()
            z = max(target[2], floor + 0.003 - p_o[2] - low)  # the hand's lowest point clears the floor
            if z <= highest:
                target[2] = z
                break
        else:
            return None
    else:
        if _boxy(obj):
            direction = _snap_to_faces(direction, r_o)
        normal = -UP
        thumb = np.cross(direction, normal) if side == "right" else np.cross(normal, direction)
        rot_w = hand.orientation(normal, thumb)
        pitch = rng.uniform(0.0, 0.3) * min(1.0, hz / 0.05)  # fingers tip down
        rot_w = axis_angle(thumb, pitch if side == "right" else -pitch) @ rot_w
        target = np.array([0.0, 0.0, hz])
        lam = float(np.interp(obj.half_extents[:2].max(), [0.025, 0.06], [0.9, 0.6]))
    return make_grasp(hand, obj.shape, verts, r_o.T @ rot_w, target, r_o.T @ normal, lam, obstacles)


def grasp_styles(obj: ObjectSpec, rng: np.random.Generator) -> list[str]:
    """Styles to try, the object's preferred one first (short side-grasp objects may be
    taken from the top now and then)."""
    if obj.grasp == "top":
        return ["top"]
    if obj.handle is None and obj.half_height <= 0.05 and rng.random() < 0.25:
        return ["top", "side"]
    return ["side", "top"] if obj.handle is None else ["side"]


def world_pose(obj_pose, grasp: Grasp) -> tuple[np.ndarray, np.ndarray]:
    """World wrist pose of a grasp on the object at ``obj_pose``."""
    r_o, p_o = obj_pose
    return r_o @ grasp.rot, p_o + r_o @ grasp.pos


# ---- episodes and intents -----------------------------------------------------------------


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


class _Builder:
    """Builds one plan; the intent methods add the object keys of the manipulation."""

    def __init__(self, scene: Scene, obj: ObjectSpec, verts: np.ndarray, intent: str, mode: str,
                 rng: np.random.Generator):
        self.scene, self.obj, self.rng, self.mode = scene, obj, rng, mode
        self.plan = Plan(scene, obj, verts, intent, mode, PoseTrack(),
                         {s: HandPlan(s, scene.relaxed[s]) for s in SIDES}, Track(), Track())
        for hp in self.plan.hands.values():
            hp.key(0.0, IDLE)
        self.plan.look.key(0.0, 0.0)
        self.plan.pitch.key(0.0, 0.0)
        self.u = rng.uniform
        self.tempo = rng.uniform(0.75, 1.15)  # a slow or brisk performer

    def d(self, lo: float, hi: float) -> float:
        """A random phase duration (s) at this sequence's tempo."""
        return self.tempo * self.u(lo, hi)

    # -- helpers

    def key(self, t: float, rot: np.ndarray, pos: np.ndarray) -> float:
        self.plan.object.key(t, rot, pos)
        return snap(t)

    def reachable(self, side: str, grasp: Grasp, obj_pose, margin: float = 0.1) -> bool:
        """Within reach with a bow short of the deepest, and the wrist still in front of the
        shoulder (a bow over a spot close to the body would reach back for it)."""
        sc = self.scene
        wrist = world_pose(obj_pose, grasp)[1]
        psi = sc.psi_toward(obj_pose[1])
        theta = sc.required_bend(side, wrist[None], np.array([psi]))[0]
        shoulder = sc.torso(theta, psi).point(sc.rest, sc.arms[side].shoulder)
        return bool(theta <= THETA_MAX - margin and wrist[1] - shoulder[1] >= 0.05)

    def comfortable(self, rot: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``rot`` turned about the vertical so that the (first) holding hand points roughly
        along its arm's line toward ``target``: the wrist then need not bend far."""
        hp = next(hp for hp in self.plan.hands.values() if hp.grasp is not None)
        sc = self.scene
        shoulder = sc.torso(sc.theta0, 0.0).point(sc.rest, sc.arms[hp.side].shoulder)
        have = rot @ hp.grasp.rot @ hp.grasp.hand.canonical[:, 0]
        want = target - shoulder
        angle = np.arctan2(have[0] * want[1] - have[1] * want[0], have[:2] @ want[:2])
        return axis_angle(UP, 0.8 * angle) @ rot

    def table_spot(self, where: str) -> tuple[float, float]:
        """A random (x, y) on the table in front of the subject: on one side or centred."""
        sc = self.scene
        x = self.u(-0.05, 0.05) if where == "centre" else side_sign(where) * self.u(0.08, 0.32)
        return sc.pelvis[0] + x, sc.near_edge + self.u(0.08, 0.22)

    def put_down(self, pose) -> tuple[np.ndarray, np.ndarray]:
        """Upright pose on the table near ``pose`` (a few cm away, slightly turned)."""
        r, p = pose
        return axis_angle(UP, self.u(-0.2, 0.2)) @ r, p + np.array([self.u(-0.04, 0.04), self.u(-0.04, 0.04), 0.0])

    def lower(self, t: float, pose) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
        """Object keys that bring the held object over its spot on the table, then set it
        down there (so it does not sweep along the bowing chest); returns (time, pose)."""
        r, p = pose
        t = self.key(t + self.d(0.6, 1.0), r, p + self.u(0.06, 0.12) * UP)
        return self.key(t + self.d(0.35, 0.55), r, p), pose

    def table_grasps(self, sides: tuple[str, ...], where: str, styles: list[str] | None = None):
        """Place the object on the table and grasp it with ``sides`` (the given styles, else
        the object's); retried with other draws until every grasp is found and in reach."""
        sc, obj = self.scene, self.obj
        for _ in range(8):
            base = {s: {"side": unit(np.array([side_sign(s), -0.35 if where == "centre" else -1.0, 0.0])),
                        "top": unit(np.array([0.3 * side_sign(s), 1.0, 0.0]))} for s in sides}
            if obj.handle is not None:  # turn the handle toward the (single) hand
                yaw = np.arctan2(base[sides[0]]["side"][1], base[sides[0]]["side"][0]) + self.u(-0.3, 0.3)
            elif len(sides) == 2:  # faces toward both hands
                yaw = self.u(-0.25, 0.25)
            else:
                yaw = self.u(0.0, 2 * np.pi)
            pose = sc.on_table(obj, *self.table_spot(where), yaw)
            table = floor_plane(*pose, sc.table_height)
            obstacles = Obstacles((table,))
            grasps = {}
            if styles is None:
                styles = ["side"] if len(sides) == 2 else grasp_styles(obj, self.rng)  # two hands: at the sides
            for s in sides:
                g = _first_grasp(sc, s, obj, self.plan.shape_verts, pose, self.rng, base[s],
                                 0.15 if where == "centre" else 0.4, obstacles, sc.table_height,
                                 obj.handle is not None, styles)
                if g is None or not self.reachable(s, g, pose):
                    break
                grasps[s] = g
                obstacles = g.obstacles((table,))
            else:
                return pose, grasps
        raise PlanRejected(f"no reachable {'+'.join(sides)} grasp of {obj.name} on the table")

    def extend(self, rot: np.ndarray, base: np.ndarray, direction: np.ndarray, frac: float) -> np.ndarray:
        """Object position along ``base + s * direction`` at which the farthest holding wrist
        is ``frac`` of its arm's length from its shoulder (the arm almost straight)."""
        tor = self.scene.torso(self.scene.theta0, 0.0)
        hands = [(hp.side, hp.grasp) for hp in self.plan.hands.values() if hp.grasp is not None]

        def extension(s):
            p = base + s * direction
            return max(np.linalg.norm(p + rot @ g.pos - tor.point(self.scene.rest, self.scene.arms[side].shoulder))
                       / self.scene.arms[side].reach for side, g in hands)

        lo, hi = 0.0, 1.0
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if extension(mid) < frac else (lo, mid)
        return base + lo * direction

    def shoulder_height(self) -> float:
        tor = self.scene.torso(self.scene.theta0, 0.0)
        return float(np.mean([tor.point(self.scene.rest, a.shoulder)[2] for a in self.scene.arms.values()]))

    # -- flows

    def one_or_both(self, manipulate) -> None:
        sides = SIDES if self.mode == "both" else (self.mode,)
        pose0, grasps = self.table_grasps(sides, "centre" if self.mode == "both" else self.mode)
        t0 = self.d(0.3, 0.7)
        self.plan.look.key(t0 + 0.3, 1.0)
        closed = [grasp_in(self.plan.hands[s], t0 + (self.d(0.0, 0.15) if i else 0.0), grasps[s], pose0, self.rng,
                           self.tempo)
                  for i, s in enumerate(sides)]
        t = self.key(max(closed) + self.d(0.02, 0.1), *pose0)
        t, pose_end = manipulate(t, pose0)
        t += self.d(0.05, 0.15)
        self.plan.look.key(t, 1.0)
        ends = [grasp_out(self.plan.hands[s], t + (self.d(0.0, 0.1) if i else 0.0), pose_end, self.rng,
                           self.tempo)
                for i, s in enumerate(sides)]
        self.finish(max(ends))

    def passing(self) -> None:
        giver, taker = self.mode.split(">")
        sc, obj, u = self.scene, self.obj, self.u
        # A small object taken from the top would leave the taker no room: take it low at the side.
        styles = ["side", "top"] if obj.half_height <= 0.03 else None
        pose0, grasps = self.table_grasps((giver,), giver, styles)
        t0 = self.d(0.3, 0.7)
        self.plan.look.key(t0 + 0.3, 1.0)
        t = grasp_in(self.plan.hands[giver], t0, grasps[giver], pose0, self.rng, self.tempo)
        r0, p0 = pose0
        self.key(t, r0, p0)
        t = self.key(t + self.d(0.4, 0.7), r0, p0 + np.array([0.0, u(-0.05, 0.0), u(0.08, 0.15)]))
        p_pass = np.array([sc.pelvis[0] + u(-0.04, 0.04), sc.pelvis[1] + u(0.30, 0.42),
                           self.shoulder_height() - u(0.22, 0.35)])
        r_pass = self.comfortable(r0, p_pass)
        t_arrive = self.key(t + self.d(0.6, 0.9), r_pass, p_pass)
        base = {"side": unit(np.array([side_sign(taker), -0.6, 0.0])),
                "top": unit(np.array([0.3 * side_sign(taker), 1.0, 0.0]))}
        styles = ["side", "top"] if self.rng.random() < 0.5 else ["top", "side"]
        bottom = p_pass[2] - obj.half_height  # the taker puts it down: its hand stays above
        g_taker = _first_grasp(sc, taker, obj, self.plan.shape_verts, (r_pass, p_pass), self.rng, base, 0.3,
                               grasps[giver].obstacles((floor_plane(r_pass, p_pass, bottom),)), bottom,
                               False, styles)
        if g_taker is None or not self.reachable(taker, g_taker, (r_pass, p_pass)):
            raise PlanRejected(f"no {taker} grasp to take {obj.name} over")
        t_taken = grasp_in(self.plan.hands[taker], t_arrive - self.d(0.6, 0.9), g_taker, (r_pass, p_pass),
                           self.rng, self.tempo, not_before=t_arrive + self.d(0.02, 0.15))
        t_let_go = t_taken + self.d(0.1, 0.25)
        end_giver = grasp_out(self.plan.hands[giver], t_let_go, (r_pass, p_pass), self.rng, self.tempo)
        # The giver's fingers are off before the taker moves it (its grip opens in <= 0.3 s).
        t = self.key(t_let_go + self.tempo * 0.3 + self.d(0.05, 0.15), r_pass, p_pass)
        for _ in range(8):
            drop = (axis_angle(UP, u(-0.2, 0.2)) @ r_pass,
                    np.array([*self.table_spot(taker), sc.table_height + obj.half_height]))
            if self.reachable(taker, g_taker, drop):
                break
        else:
            raise PlanRejected(f"cannot put {obj.name} down with the {taker} hand")
        t = self.lower(t, drop)[0] + self.d(0.05, 0.15)
        self.plan.look.key(t, 1.0)
        self.finish(max(end_giver, grasp_out(self.plan.hands[taker], t, drop, self.rng, self.tempo)))

    def finish(self, t: float) -> None:
        self.plan.look.key(t, 0.0)
        end = snap(t + self.d(0.3, 0.7))
        if end > MAX_SECONDS:
            raise PlanRejected(f"plan lasts {end:.2f} s")
        for hp in self.plan.hands.values():
            hp.key(end, IDLE)
        self.plan.look.key(end, 0.0)
        self.plan.pitch.key(end, 0.0)
        self.plan.duration = end

    # -- manipulations: object keys from the grip at ``t``; return (time, pose back on the table)
    #    (durations through self.d, so they follow the sequence's tempo)

    def lift(self, t: float, pose0):
        r0, p0 = pose0
        u = self.u
        up = p0 + np.array([u(-0.05, 0.05), u(-0.12, 0.0), u(0.15, 0.3)])
        tilt = axis_angle(_turn(np.array([1.0, 0.0, 0.0]), u(0, 2 * np.pi)), u(0.0, 0.12))
        t = self.key(t + self.d(0.6, 1.0), tilt @ r0, up)
        t = self.key(t + self.d(0.4, 1.2), axis_angle(UP, u(-0.15, 0.15)) @ r0, up + u(-0.03, 0.03, 3))
        return self.lower(t, self.put_down(pose0))

    def offhand(self, t: float, pose0):
        r0, p0 = pose0
        u = self.u
        t = self.key(t + self.d(0.5, 0.8), r0, p0 + np.array([0.0, u(-0.05, 0.0), u(0.08, 0.15)]))
        sc = self.scene
        base = np.array([sc.pelvis[0] + 0.5 * (p0[0] - sc.pelvis[0]), sc.pelvis[1] + 0.15,
                         self.shoulder_height() - u(0.12, 0.3)])
        direction = _turn(np.array([0.0, 1.0, 0.0]), u(-0.2, 0.2))
        r_off = r0 if self.mode == "both" else self.comfortable(r0, base + 0.4 * direction)
        p_off = self.extend(r_off, base, direction, u(0.86, 0.93))
        t = self.key(t + self.d(0.8, 1.1), r_off, p_off)
        t = self.key(t + self.d(0.8, 1.8), r_off, p_off + u(-0.02, 0.02, 3))
        return self.lower(t, self.put_down(pose0))

    def inspect(self, t: float, pose0):
        r0, p0 = pose0
        u = self.u
        t = self.key(t + self.d(0.5, 0.8), r0, p0 + np.array([0.0, u(-0.05, 0.0), u(0.1, 0.18)]))
        lateral = 0.0 if self.mode == "both" else side_sign(self.mode) * u(0.0, 0.06)
        p_face = self.scene.mouth(0.0) + np.array([lateral, u(0.26, 0.36), u(-0.06, 0.02)])
        r_face = r0 if self.mode == "both" else self.comfortable(r0, p_face)
        t = self.key(t + self.d(0.8, 1.1), r_face, p_face)
        if self.mode == "both":  # turn it like a steering wheel or about the vertical
            pivot, axes, ranges = p_face, (np.array([0.0, 1.0, 0.0]), UP), ((0.2, 0.5), (0.2, 0.5))
        else:  # turn the hand about its own axis (forearm twist), tilt it, or turn it about the vertical
            g = self.plan.hands[self.mode].grasp
            hand_rot = r_face @ g.rot
            pivot = p_face + r_face @ g.pos  # the wrist stays put
            axes = (hand_rot @ g.hand.canonical[:, 0], hand_rot @ g.hand.canonical[:, 2], UP)
            ranges = ((0.6, 1.3), (0.25, 0.5), (0.3, 0.7))
        for _ in range(int(self.rng.integers(2, 4))):
            k = int(self.rng.integers(len(axes)))
            turn = axis_angle(axes[k], self.rng.choice([-1.0, 1.0]) * u(*ranges[k]))
            t = self.key(t + self.d(0.6, 1.0), turn @ r_face, pivot + turn @ (p_face - pivot) + u(-0.02, 0.02, 3))
        t = self.key(t + self.d(0.6, 0.9), r_face, p_face)
        return self.lower(t, self.put_down(pose0))

    def drink(self, t: float, pose0):
        r0, p0 = pose0
        u, plan = self.u, self.plan
        t = self.key(t + self.d(0.5, 0.8), r0, p0 + np.array([0.0, u(-0.05, 0.0), u(0.08, 0.15)]))
        back = u(0.15, 0.35)  # the head tilts back while drinking
        mouth = self.scene.mouth(-back) + np.array([0.0, u(0.008, 0.02), 0.0])
        toward = np.array([0.0, -1.0, 0.0])  # from the object to the face
        axis = np.cross(UP, toward)
        lip = edge_point(self.obj.shape, np.array([0.0, 0.0, self.obj.half_height - 0.003]), r0.T @ toward)
        r_near = axis_angle(axis, u(0.1, 0.3)) @ r0
        r_sip = axis_angle(axis, u(0.8, 1.25)) @ r0
        p_sip = mouth - r_sip @ lip
        p_near = p_sip + np.array([0.0, u(0.04, 0.08), -u(0.10, 0.16)])
        t = self.key(t + self.d(0.8, 1.1), r_near, p_near)
        plan.look.key(t, 1.0)
        plan.pitch.key(t, 0.0)
        t = self.key(t + self.d(0.5, 0.8), r_sip, p_sip)
        plan.look.key(t, 0.0)
        plan.pitch.key(t, -back)
        r_sip2 = axis_angle(axis, u(0.0, 0.2)) @ r_sip
        t = self.key(t + self.d(0.8, 1.6), r_sip2, mouth - r_sip2 @ lip)
        plan.look.key(t, 0.0)
        plan.pitch.key(t, -back)
        t = self.key(t + self.d(0.5, 0.8), r_near, p_near)
        plan.look.key(t, 1.0)
        plan.pitch.key(t, 0.0)
        return self.lower(t, self.put_down(pose0))

    def pour(self, t: float, pose0):
        r0, p0 = pose0
        u, sc = self.u, self.scene
        t = self.key(t + self.d(0.5, 0.8), r0, p0 + np.array([0.0, u(-0.05, 0.0), u(0.08, 0.15)]))
        if self.mode == "both":
            toward, alpha = np.array([0.0, 1.0, 0.0]), u(0.8, 1.15)
            spot = p0 + np.array([u(-0.05, 0.05), u(0.12, 0.2), 0.0])
        else:  # tip it over forward, about the (level) line of the arm: a twist of the forearm
            shoulder = sc.torso(sc.theta0, 0.0).point(sc.rest, sc.arms[self.mode].shoulder)
            toward = np.cross(UP, world_pose(pose0, self.plan.hands[self.mode].grasp)[1] - shoulder)
            toward = unit(toward * np.array([1.0, 1.0, 0.0]) * np.sign(toward[1]))
            alpha = u(1.1, 1.6)
            spot = p0 + u(0.15, 0.28) * toward
        c = sc.table_centre
        spot[0] = np.clip(spot[0], c[0] - TABLE_SIZE[0] / 2 + 0.05, c[0] + TABLE_SIZE[0] / 2 - 0.05)
        spot[1] = np.clip(spot[1], sc.near_edge + 0.05, c[1] + TABLE_SIZE[1] / 2 - 0.05)
        spot[2] = sc.table_height
        axis = np.cross(UP, toward)
        spout = edge_point(self.obj.shape, np.array([0.0, 0.0, self.obj.half_height - 0.003]), r0.T @ toward)
        height = u(0.12, 0.2)

        def tilted(angle):
            rot = axis_angle(axis, angle) @ r0
            pos = spot + height * UP - rot @ spout
            low = (self.plan.shape_verts @ rot.T + pos)[:, 2].min() - sc.table_height
            return rot, pos + max(0.04 - low, 0.0) * UP  # keep the tilted object off the table

        r_pre, p_pre = tilted(u(0.15, 0.3))
        t = self.key(t + self.d(0.7, 1.0), r_pre, p_pre - 0.03 * toward + 0.04 * UP)
        t = self.key(t + self.d(0.5, 0.8), *tilted(alpha))
        t = self.key(t + self.d(0.8, 1.6), *tilted(alpha + u(0.0, 0.2)))
        t = self.key(t + self.d(0.5, 0.8), r_pre, p_pre - 0.03 * toward + 0.04 * UP)
        return self.lower(t, self.put_down(pose0))


def _first_grasp(scene, side, obj, verts, pose, rng, base, spread, obstacles, floor, handle, styles) -> Grasp | None:
    """A few randomized attempts per style around the style's base direction."""
    for style in styles:
        for _ in range(4):
            g = try_grasp(scene, side, obj, verts, pose, style, _turn(base[style], rng.uniform(-spread, spread)),
                          rng, obstacles, floor, handle)
            if g is not None:
                return g
    return None


def make_plan(model: SubjectModel, obj: ObjectSpec, verts: np.ndarray, intent: str, mode: str,
              rng: np.random.Generator) -> Plan:
    """Sample a scene and plan one sequence; raises PlanRejected when this draw fails."""
    b = _Builder(make_scene(model, rng), obj, verts, intent, mode, rng)
    if intent == "pass":
        b.passing()
    else:
        b.one_or_both(getattr(b, intent))
    return b.plan
