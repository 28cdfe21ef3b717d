"""The engine's contact-consistency stage (``src/contact.rs``), as the Python reference.

The engine rewrites every frame of a stream so that the object obeys the hands: contact
debounced, an unheld object resting (or falling onto its support), a reach correction
(two-bone arm IK plus a spine bow) that brings the wrist to the object when a grasp
starts, the object carried rigidly while held. ``evaluate`` runs it over PyTorch's output
so that the raw and the consistent motion are measured side by side, and
``tests/fixtures/contact_stage`` pins this code and the engine's to the same frames
(``training/tests/test_contact_stage.py`` here, ``tests/contact_stage.rs`` there).

This is a line-by-line port: same constants, same order of operations, float64 on frames
decoded from float32 features, so the engine's frames match within the manifest's
``frames`` tolerance. docs/engine.md ("Contact consistency") says what the rules are and
why; the comments here only mark where the code must stay in step with the Rust.
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import skeleton as sk
from .layout import CONTACT_CHANNELS, FIELD, FRAME_DIM, ROT6D_JOINT_COLUMNS

ON_FRAMES = 2
OFF_FRAMES = 4
REACH_SPEED = 0.6
MIN_REACH_FRAMES = 4
MAX_REACH_FRAMES = 30
FADE_SPEED = 0.3
REACH_LIMIT = 0.98
REACH_MISS = 0.02
REGRIP = 0.01
GRIP_GAP = 0.005
GRIP_SCAN_STEPS = 12
GRIP_SEARCH_STEPS = 8
SURFACE_SPACING = 0.01
GRIP_MARGIN = 0.12
PALM = (0, 1, 4, 7, 10, 13)  # hand_offsets rows: the wrist and each finger's base joint
MAX_BOW = 0.6
BOW_REACH = 0.94
BOW_FADE = 0.5
BOW_SPEED = 1.5
SPINE = (3, 6, 9)
TABLE_NEAR = 0.15
TABLE_FAR = 1.1
TABLE_HALF_WIDTH = 0.7
SUPPORT_RADIUS = 0.3
TABLE_MIN_HEIGHT = 0.05
LIFT_CLEAR = 0.03
SUPPORT_DEPTH = 0.1
GROUND_Z = 0.0
GRAVITY = 9.81
MAX_SPEED = 2.0
LIMIT_TRIES = 4
LANDED = 1e-9
TURN_FADE = 1.0
TIP_SPEED = 3.0
PRESS_UP_SPEED = 0.6
LEVEL_HEIGHT = 0.1
LEVEL_SPEED = 6.0
SET_DOWN_SPEED = 0.1
PLACE_HEIGHT = 0.2
PUT_DOWN_FRAMES = 3
SET_DOWN_TILT = 2.0 * math.pi / 180.0
CONTACT_THRESHOLD = 0.5
PLACE_LOOKAHEAD = 128
GROUND_TOE_HEIGHT = 0.034
GROUND_SPEED = 0.5
STANDING = 0.5
TOES = (10, 11)
NORM_EPS = 1e-12

ARMS = ((13, 16, 18, 20), (14, 17, 19, 21))
# Planted feet (``feet.rs``): legs as (pelvis, hip, knee, ankle), left then right.
LEGS = ((0, 1, 4, 7), (0, 2, 5, 8))
PLANT_SPEED = 0.25
FOOT_LIFT = 0.05
FOOT_STEP = 0.3
FOOT_TURN = 0.8
FOOT_FADE = 0.3
FOOT_TURN_FADE = 1.0
HAND_FIRST = (25, 40)
LIMITED = (ARMS[0][3], ARMS[1][3], *range(HAND_FIRST[0], HAND_FIRST[0] + 30))
IDENTITY = np.eye(3)


# ---- small geometry, as src/skeleton.rs --------------------------------------------------


def _norm(v: np.ndarray) -> float:
    return math.sqrt(float(v @ v))


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    s, c = math.sin(angle), math.cos(angle)
    t = 1.0 - c
    x, y, z = axis
    return np.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                     [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                     [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


def orthogonal(v: np.ndarray) -> np.ndarray:
    e = np.zeros(3)
    e[int(np.argmin(np.abs(v)))] = 1.0
    c = np.cross(v, e)
    return c / _norm(c)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    na, nb = _norm(a), _norm(b)
    if not (na > NORM_EPS and nb > NORM_EPS):
        return IDENTITY.copy()
    a, b = a / na, b / nb
    axis = np.cross(a, b)
    s, c = _norm(axis), float(a @ b)
    if s > 1e-12:
        return axis_angle(axis / s, math.atan2(s, c))
    return IDENTITY.copy() if c > 0.0 else axis_angle(orthogonal(a), math.pi)


def rot6d_to_matrix(d: np.ndarray) -> np.ndarray:
    """6D (first two rows) -> rotation, with the engine's fallbacks for degenerate input."""
    a1, a2 = d[:3], d[3:]
    n1 = _norm(a1)
    b1 = a1 / n1 if n1 > NORM_EPS and math.isfinite(n1) else np.array([1.0, 0.0, 0.0])
    a2 = a2 if np.isfinite(a2).all() else np.zeros(3)
    r = a2 - float(b1 @ a2) * b1
    n2 = _norm(r)
    b2 = r / n2 if n2 > NORM_EPS and math.isfinite(n2) else orthogonal(b1)
    return np.stack((b1, b2, np.cross(b1, b2)))


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Rotation -> unit quaternion (x, y, z, w), w >= 0 (Shepperd, as the engine)."""
    t = (1.0 + m[0, 0] + m[1, 1] + m[2, 2], 1.0 + m[0, 0] - m[1, 1] - m[2, 2],
         1.0 - m[0, 0] + m[1, 1] - m[2, 2], 1.0 - m[0, 0] - m[1, 1] + m[2, 2])
    best = max(range(4), key=lambda i: (t[i], -i))
    s = math.sqrt(max(t[best], 0.0)) or 1.0
    if best == 0:
        w, x, y, z = s * s, m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]
    elif best == 1:
        w, x, y, z = m[2, 1] - m[1, 2], s * s, m[1, 0] + m[0, 1], m[0, 2] + m[2, 0]
    elif best == 2:
        w, x, y, z = m[0, 2] - m[2, 0], m[1, 0] + m[0, 1], s * s, m[1, 2] + m[2, 1]
    else:
        w, x, y, z = m[1, 0] - m[0, 1], m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], s * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (math.isfinite(n) and n > 0.0):
        return np.array([0.0, 0.0, 0.0, 1.0])
    k = (-1.0 if w < 0.0 else 1.0) / n
    return np.array([x * k, y * k, z * k, w * k])


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def smoothstep(t: float) -> float:
    t = min(max(t, 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


class Skeleton:
    """The bundle's skeleton (SMPL-X parents, rest joints): FK as the engine does it."""

    def __init__(self, rest_joints: np.ndarray, parents: tuple[int, ...] = sk.PARENTS):
        self.parents = tuple(int(p) for p in parents)
        self.rest = np.asarray(rest_joints, dtype=np.float32).astype(np.float64)
        self.offsets = self.rest.copy()
        for j in range(1, sk.NUM_JOINTS):
            self.offsets[j] = self.rest[j] - self.rest[self.parents[j]]

    def forward(self, local: np.ndarray, pelvis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        glob = np.empty((sk.NUM_JOINTS, 3, 3))
        pos = np.empty((sk.NUM_JOINTS, 3))
        glob[0], pos[0] = local[0], pelvis
        for j in range(1, sk.NUM_JOINTS):
            p = self.parents[j]
            pos[j] = pos[p] + glob[p] @ self.offsets[j]
            glob[j] = glob[p] @ local[j]
        return glob, pos

    def arm_length(self, h: int) -> float:
        _, s, e, w = ARMS[h]
        return _norm(self.rest[e] - self.rest[s]) + _norm(self.rest[w] - self.rest[e])


# ---- frames ------------------------------------------------------------------------------


@dataclass
class Pose:
    """One frame in the native world (z up, metres), as ``assemble::Pose``."""

    local: np.ndarray  # (55, 3, 3); 0 = the root's global rotation
    pelvis: np.ndarray
    object_rotation: np.ndarray
    object_translation: np.ndarray
    object_centre: np.ndarray
    wrist_to_object: np.ndarray  # (2, 3) [left, right]
    contact_probability: np.ndarray  # (2,)
    contact: np.ndarray  # (2,) bool

    @staticmethod
    def from_features(x: np.ndarray) -> Pose:
        """A de-normalized 335-D frame (float32 values, as the engine decodes them)."""
        f = np.asarray(x, dtype=np.float32).astype(np.float64)
        local = np.tile(IDENTITY, (sk.NUM_JOINTS, 1, 1))
        for j, col in ROT6D_JOINT_COLUMNS.items():
            local[j] = rot6d_to_matrix(f[col:col + 6])
        prob = np.clip(np.nan_to_num(f[list(CONTACT_CHANNELS)], nan=0.0), 0.0, 1.0)
        return Pose(local, f[FIELD["root_transl"].slice].copy(), rot6d_to_matrix(f[FIELD["object_rot6d"].slice]),
                    f[FIELD["object_transl"].slice].copy(), f[FIELD["object_centre"].slice].copy(),
                    np.stack((f[FIELD["lwrist_to_object"].slice], f[FIELD["rwrist_to_object"].slice])),
                    prob, prob > CONTACT_THRESHOLD)

    def to_features(self) -> np.ndarray:
        """Back to 335-D; the contact channels carry the stage's held flags (0 or 1)."""
        x = np.zeros(FRAME_DIM)
        for j, col in ROT6D_JOINT_COLUMNS.items():
            x[col:col + 6] = self.local[j][:2].reshape(6)
        x[FIELD["root_transl"].slice] = self.pelvis
        x[FIELD["object_rot6d"].slice] = self.object_rotation[:2].reshape(6)
        x[FIELD["object_transl"].slice] = self.object_translation
        x[FIELD["object_centre"].slice] = self.object_centre
        x[FIELD["lwrist_to_object"].slice] = self.wrist_to_object[0]
        x[FIELD["rwrist_to_object"].slice] = self.wrist_to_object[1]
        x[list(CONTACT_CHANNELS)] = self.contact.astype(np.float64)
        return x


def read_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """``v`` and ``f`` lines of an OBJ mesh (as ``bundle::obj::parse``): float32 vertices and
    fan-triangulated faces (0-based; negative references are relative)."""
    vertices, triangles = [], []
    for line in text.splitlines():
        words = line.split("#")[0].split()
        if words[:1] == ["v"]:
            vertices.append([np.float32(w) for w in words[1:4]])
        elif words[:1] == ["f"]:
            idx = [int(w.split("/")[0]) for w in words[1:]]
            idx = [i - 1 if i > 0 else len(vertices) + i for i in idx]
            triangles += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    return np.asarray(vertices, np.float32).reshape(-1, 3), np.asarray(triangles, np.int64).reshape(-1, 3)


def surface_from_mesh(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Surface samples (points, outward unit normals; object frame) as
    ``contact::ObjectSurface::from_mesh``: corners turned so that ``ab`` is the shortest
    edge, a grid of ``ceil(|ab|/s)`` by ``ceil(|ac|/s)`` samples (``s = SURFACE_SPACING``)."""
    v = np.asarray(vertices, np.float32).astype(np.float64)
    points, normals = [], []
    for t in np.asarray(triangles):
        c = v[t]
        edges = [_norm(c[(k + 1) % 3] - c[k]) for k in range(3)]
        first = 0
        for k in (1, 2):
            if edges[k] < edges[first]:
                first = k
        a, b, cc = c[first], c[(first + 1) % 3], c[(first + 2) % 3]
        ab, ac = b - a, cc - a
        n = np.cross(ab, ac)
        area2 = _norm(n)
        longest = max(edges)
        if not (area2 > 1e-12 * longest * longest and math.isfinite(area2)):
            continue
        n1 = max(math.ceil(_norm(ab) / SURFACE_SPACING), 1)
        n2 = max(math.ceil(_norm(ac) / SURFACE_SPACING), 1)
        u = np.repeat((np.arange(n1) + 0.5) / n1, n2)[:, None]
        w = (1.0 - u) * np.tile((np.arange(n2) + 0.5) / n2, n1)[:, None]
        points.append(a + (ab * u + ac * w))
        normals.append(np.broadcast_to(n * (1.0 / area2), (n1 * n2, 3)))
    return np.concatenate(points), np.concatenate(normals)


def box_distances(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distances of points (..., 3) (from the box centre, box frame) to a box."""
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


@dataclass(frozen=True)
class ObjectShape:
    """The object's box in its own frame (bounding-box centre and half extents, m) and,
    when known, samples of its surface (points, normals), as ``contact::ObjectShape``."""

    centre: np.ndarray
    half_extents: np.ndarray
    surface: tuple[np.ndarray, np.ndarray] | None = None

    @staticmethod
    def of(centre, half_extents, surface=None) -> ObjectShape:
        # The bundle stores both as float32, and so do the fixtures.
        return ObjectShape(np.asarray(centre, np.float32).astype(np.float64),
                           np.abs(np.asarray(half_extents, np.float32).astype(np.float64)), surface)

    @staticmethod
    def for_meta(meta: dict) -> ObjectShape:
        """A prepared sequence's object as a bundle carries it: a catalogue object's entry
        (mesh bounds centre, the catalogue's half extents) and the surface of the mesh the
        bundle ships; another object's mesh, its bounds and surface."""
        from .objects.catalogue import CATALOGUE

        name = meta.get("object", "")
        if name in CATALOGUE:
            return _catalogue_shape(name)
        import trimesh

        m = trimesh.load(Path(meta["object_mesh"]), force="mesh", process=False)
        lo, hi = m.bounds
        return ObjectShape.of((lo + hi) / 2.0, (hi - lo) / 2.0, surface_from_mesh(m.vertices, m.faces))

    def distance(self, p: np.ndarray) -> np.ndarray:
        """How far points (..., 3) (from the box centre, object frame) are outside the
        object: the box distance, or the surface distance where that is larger."""
        d = box_distances(p, self.half_extents)
        if self.surface is None:
            return d
        points, normals = self.surface
        q = np.asarray(p) + self.centre
        d2 = ((q[..., None, :] - points) ** 2).sum(-1)
        nearest = np.argmin(d2, axis=-1)
        along = ((q - points[nearest]) * normals[nearest]).sum(-1)
        # beyond the nearest sample's patch: the distance from its rim (a torus's hole)
        beyond = np.maximum(np.sqrt(np.maximum(np.take_along_axis(d2, nearest[..., None], -1)[..., 0] - along * along,
                                                0.0)) - SURFACE_SPACING, 0.0)
        surface = np.where(beyond > 0.0, np.sign(along) * np.sqrt(along * along + beyond * beyond), along)
        return np.maximum(d, surface)

    def centre_at(self, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        return pos + rot @ self.centre

    def point_at(self, rot: np.ndarray, pos: np.ndarray, local: np.ndarray) -> np.ndarray:
        return self.centre_at(rot, pos) + rot @ local

    def bottom_at(self, rot: np.ndarray, pos: np.ndarray) -> float:
        return float(self.centre_at(rot, pos)[2] - sum(abs(rot[2, k]) * self.half_extents[k] for k in range(3)))


def heading(pelvis: np.ndarray, root: np.ndarray, toward: np.ndarray) -> np.ndarray:
    f = root @ np.array([0.0, 0.0, 1.0])
    to = toward[:2] - pelvis[:2]
    fl, tl = math.hypot(f[0], f[1]), math.hypot(to[0], to[1])
    if fl > 0.5:
        return np.array([f[0] / fl, f[1] / fl])
    if tl > 1e-6:
        return to / tl
    return np.array([0.0, 1.0])


@dataclass(frozen=True)
class Table:
    """The support the object starts on (``contact::Table``)."""

    height: float
    start: np.ndarray
    origin: np.ndarray
    forward: np.ndarray

    @staticmethod
    def new(pelvis, root, object_rot, object_pos, shape: ObjectShape) -> Table:
        c = shape.centre_at(object_rot, object_pos)
        bottom = shape.bottom_at(object_rot, object_pos)
        height = GROUND_Z if bottom < GROUND_Z + TABLE_MIN_HEIGHT else bottom
        return Table(height, c[:2].copy(), np.asarray(pelvis[:2], np.float64).copy(), heading(pelvis, root, c))

    def is_ground(self) -> bool:
        return self.height <= GROUND_Z

    def over(self, p: np.ndarray) -> bool:
        if self.is_ground():
            return False
        dx, dy = p[0] - self.start[0], p[1] - self.start[1]
        fx, fy = self.forward
        rx, ry = p[0] - self.origin[0], p[1] - self.origin[1]
        ahead = rx * fx + ry * fy
        side = abs(rx * fy - ry * fx)
        return math.hypot(dx, dy) <= SUPPORT_RADIUS or (TABLE_NEAR <= ahead <= TABLE_FAR and side <= TABLE_HALF_WIDTH)


# ---- the stage ---------------------------------------------------------------------------


@dataclass
class _Reach:
    frame: int
    frames: int
    start: np.ndarray  # the correction when the reach started
    bow_from: float
    grip: np.ndarray  # wrist minus object centre, object frame
    again: bool = False  # a re-aim (at most one per grasp)


@dataclass
class _Hand:
    on: int = 0
    off: int = 0
    phase: str = "free"  # "free" | "reaching" | "holding"
    reach: _Reach | None = None
    correction: np.ndarray = field(default_factory=lambda: np.zeros(3))
    latched: bool = False
    rel_rot: np.ndarray = field(default_factory=lambda: IDENTITY.copy())
    rel_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    turn: np.ndarray = field(default_factory=lambda: IDENTITY.copy())
    put_down: int = 0  # frames held on past the release to put the object down


@dataclass
class _Limited:
    local: np.ndarray
    pelvis: np.ndarray
    joints: np.ndarray  # the LIMITED joints
    wrists: list  # global rotation per wrist (positions: joints[0], joints[1])


@dataclass
class _Foot:
    planted: bool = False
    at: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the pinned ankle
    rot: np.ndarray = field(default_factory=lambda: IDENTITY.copy())
    correction: np.ndarray = field(default_factory=lambda: np.zeros(3))  # shown = model + correction
    turn: np.ndarray = field(default_factory=lambda: IDENTITY.copy())  # shown = turn @ model
    last: np.ndarray | None = None  # the model's ankle in the previous frame


class Feet:
    """Planted feet (``feet::Feet``): a foot the model stands on keeps its place and turn."""

    def __init__(self, fps: float, events: Counter):
        self.dt = 1.0 / fps
        self.feet = [_Foot(), _Foot()]
        self.lowest = math.inf
        self.events = events

    def apply(self, local: np.ndarray, glob: np.ndarray, joints: np.ndarray) -> None:
        for leg in LEGS:
            self.lowest = min(self.lowest, float(joints[leg[3]][2]))
        for foot, leg in zip(self.feet, LEGS):
            model, g = joints[leg[3]].copy(), glob[leg[3]]
            if foot.planted:
                away = _norm((model - foot.at)[:2]) > FOOT_STEP
                up = model[2] > foot.at[2] + FOOT_LIFT
                turned = rotation_angle(foot.rot @ g.T) > FOOT_TURN
                hip, knee = joints[leg[1]], joints[leg[2]]
                short = _norm(foot.at - hip) > _norm(knee - hip) + _norm(model - knee) + FOOT_LIFT
                foot.planted = not (away or up or turned or short)
                if not foot.planted:
                    self.events["foot_freed"] += 1
            else:
                speed = 0.0 if foot.last is None else _norm((model - foot.last)[:2]) / self.dt
                if speed <= PLANT_SPEED and model[2] <= self.lowest + FOOT_LIFT:
                    foot.planted = True
                    foot.at = model + foot.correction
                    foot.rot = foot.turn @ g
                    self.events["foot_planted"] += 1
            foot.last = model
            if foot.planted:
                foot.correction = foot.at - model
                foot.turn = foot.rot @ g.T
            else:
                n, step = _norm(foot.correction), FOOT_FADE * self.dt
                foot.correction = foot.correction * ((n - step) / n) if n > step else np.zeros(3)
                foot.turn = fade_rotation(foot.turn, FOOT_TURN_FADE * self.dt)
            if foot.correction.any() or not np.array_equal(foot.turn, IDENTITY):
                limb_ik(local, glob, joints, leg, model + foot.correction, foot.turn @ g)


class ContactStage:
    """One stream's contact state; feed every frame in order (``apply``), then ``finish``
    the last one. ``feet=False``: the legs stay the model's (``CG_STREAM_FREE_FEET``)."""

    def __init__(self, shape: ObjectShape, fps: float, feet: bool = True):
        self.shape = shape
        self.dt = 1.0 / fps
        self.started = False
        self.rot = IDENTITY.copy()
        self.pos = np.zeros(3)
        self.fall = 0.0
        self.table = Table(GROUND_Z, np.zeros(2), np.zeros(2), np.array([0.0, 1.0]))
        self.lifted = False
        self.hands = [_Hand(), _Hand()]
        self.bow = 0.0
        self.bow_axis = np.array([1.0, 0.0, 0.0])
        self.limited: _Limited | None = None
        self.released = False
        self.base = np.array([0.0, 0.0, -1.0])
        self.carried_by = [False, False]  # hands that moved the object this frame (contact shows)
        self.pressing = False  # a lifted object held up on the top while levelled
        # How often each rule fired (the reference only: tests check what a fixture covers).
        self.events: Counter[str] = Counter()
        self.feet = Feet(fps, self.events) if feet else None
        self.lift: float | None = None  # the ground lift, fixed by the first frame
        self.drop = 0.0  # how far a body the model lifts off the ground is lowered now (<= 0)
        self.standing = False  # the first frame's body stood (else neither lifted nor lowered)

    def holding(self) -> list[bool]:
        return [h.phase == "holding" for h in self.hands]

    def ground(self, skel: Skeleton, pose: Pose) -> None:
        """Raises the model's world (body and object) by one lift per stream, fixed by the
        first frame, so that its lower toe joint stands GROUND_TOE_HEIGHT above the ground,
        and lowers a body the model lifts off it later at GROUND_SPEED (``ContactStage::
        ground``); every frame, before anything else reads it."""
        toe = min(float(skel.forward(pose.local, pose.pelvis)[1][j][2]) for j in TOES)
        if not math.isfinite(toe):
            return
        if self.lift is None:
            self.standing = float(pose.pelvis[2]) - toe >= STANDING
            self.lift = GROUND_Z + GROUND_TOE_HEIGHT - toe if self.standing else 0.0
        if not self.standing:
            return
        float_ = min(GROUND_Z + GROUND_TOE_HEIGHT - (toe + self.lift), 0.0)
        step = GROUND_SPEED * self.dt
        self.drop += min(max(float_ - self.drop, -step), step)
        if self.drop < 0.0:
            self.events["ground_drop_frames"] += 1
        pose.pelvis = pose.pelvis + np.array([0.0, 0.0, self.lift + self.drop])
        up = np.array([0.0, 0.0, self.lift])
        pose.object_translation = pose.object_translation + up
        pose.object_centre = pose.object_centre + up

    def place(self, pose: Pose, centre: np.ndarray) -> None:
        """Moves the first frame's object so that its box centre lies at ``centre`` (the raw
        frame's; raised by the ground lift here), its rotation kept; after ``ground``, before
        the first ``apply``."""
        centre = centre + np.array([0.0, 0.0, self.lift or 0.0])
        d = centre - self.shape.centre_at(pose.object_rotation, pose.object_translation)
        pose.object_translation = pose.object_translation + d
        pose.object_centre = pose.object_centre + d

    def apply(self, skel: Skeleton, pose: Pose) -> None:
        glob, joints = skel.forward(pose.local, pose.pelvis)
        if not self.started:
            self.started = True
            self.rot, self.pos = pose.object_rotation.copy(), pose.object_translation.copy()
            self.table = Table.new(pose.pelvis, pose.local[0], self.rot, self.pos, self.shape)
            self.base = lowest_axis(self.rot)
        glob, joints = self._limit_speed(skel, pose, glob, joints)

        for h in range(2):
            wrist = joints[ARMS[h][3]]
            arm = skel.arm_length(h)
            hand = self.hands[h]
            if pose.contact[h]:
                hand.on, hand.off, hand.put_down = hand.on + 1, 0, 0
            else:
                hand.off, hand.on = hand.off + 1, 0
            hand.latched = hand.latched and hand.off < OFF_FRAMES
            if hand.phase == "reaching" and hand.off >= OFF_FRAMES:
                hand.phase, hand.reach = "free", None
                self.events["reach_abandoned"] += 1
            elif hand.phase == "free" and hand.on >= ON_FRAMES and not hand.latched:
                reach = self._reach(h, pose.wrist_to_object[h], joints, wrist, wrist + hand.correction, arm, False)
                if reach is not None:
                    hand.phase, hand.reach = "reaching", reach
                    self.events["reach"] += 1
                else:
                    self.events["out_of_reach"] += 1

        bow = None
        for h in range(2):
            r = self.hands[h].reach
            if self.hands[h].phase != "reaching":
                continue
            r.frame += 1
            s = smoothstep(r.frame / r.frames)
            target = self.shape.point_at(self.rot, self.pos, r.grip)
            need = needed_bow(joints, h, target, BOW_REACH * skel.arm_length(h))
            need, axis = need if need is not None else (MAX_BOW, bow_axis(joints, target))
            angle = r.bow_from + (need - r.bow_from) * s
            if bow is None or angle > bow[0]:
                bow = (angle, axis)
        if bow is not None:
            # the bow as a vector (angle along its axis) moves at most BOW_SPEED: neither its
            # size nor its direction jumps
            now, want = self.bow_axis * self.bow, bow[1] * bow[0]
            d, most = want - now, BOW_SPEED * self.dt
            n = _norm(d)
            nxt = now + d * (most / n) if n > most else want
            size = _norm(nxt)
            self.bow = size
            if size > 1e-12:
                self.bow_axis = nxt * (1.0 / size)
        else:
            self.bow = max(self.bow - BOW_FADE * self.dt, 0.0)
        if self.bow > 0.0:
            self.events["bow_frames"] += 1
            step = axis_angle(self.bow_axis, self.bow / len(SPINE))
            for j in SPINE:
                gp = glob[skel.parents[j]]
                pose.local[j] = (gp.T @ (step @ gp)) @ pose.local[j]
            glob, joints = skel.forward(pose.local, pose.pelvis)

        moved = False
        aimed = [None, None]  # where each reach puts the wrist (before the other hand moves the object)
        both = all(h.phase == "holding" for h in self.hands)
        model_wrist = [glob[arm[3]].copy() for arm in ARMS]  # turns are from these (no build-up)
        for h in range(2):
            wrist = joints[ARMS[h][3]]
            hand = self.hands[h]
            if not both:
                hand.turn = fade_rotation(hand.turn, TURN_FADE * self.dt)
            if hand.phase == "reaching":
                r = hand.reach
                s = smoothstep(r.frame / r.frames)
                aimed[h] = self.shape.point_at(self.rot, self.pos, r.grip)
                to = aimed[h] - wrist
                hand.correction = r.start * (1.0 - s) + to * s
            else:
                n = _norm(hand.correction)
                step = FADE_SPEED * self.dt
                hand.correction = hand.correction * ((n - step) / n) if n > step else np.zeros(3)
            if hand.correction.any():
                arm_ik(pose.local, glob, joints, h, wrist + hand.correction)
                moved = True
            if not np.array_equal(hand.turn, IDENTITY):
                g = glob[ARMS[h][3]]
                pose.local[ARMS[h][3]] = pose.local[ARMS[h][3]] @ (g.T @ (hand.turn @ g))
                moved = True
        if moved:
            glob, joints = skel.forward(pose.local, pose.pelvis)

        self.carried_by = self.holding()
        carried = self._carried(glob, joints)
        if carried is not None:
            was = self.pos.copy()  # a put-down and a slip keep the frame within MAX_SPEED of it
            # where it was: only an object coming down from above the top (or held up on it
            # while levelled) is set down on it
            above_before = self.pressing or self.shape.bottom_at(self.rot, self.pos) >= self.table.height
            # levelling is for setting down: coming down, not turned further over (a pour)
            def lean(r):
                return math.acos(min(1.0, max(-1.0, -float((r @ self.base)[2]))))

            sinking = self.pos[2] - carried[1][2] > SET_DOWN_SPEED * self.dt and lean(carried[0]) <= lean(self.rot)
            self.rot, self.pos, self.fall = carried[0], carried[1], 0.0
            depth = min(self.table.height - self.shape.bottom_at(*carried), PRESS_UP_SPEED * self.dt)
            tilted = leans(carried[0]) and above_before  # coming down off its face: level first
            if (not self.lifted or tilted) and depth > 0.0 and self.table.over(self.shape.centre_at(*carried)):
                self.events["press_up" if not self.lifted else "press_up_levelling"] += 1
                for h in range(2):
                    if self.hands[h].phase == "holding":
                        self.hands[h].correction[2] += depth
                        arm_ik(pose.local, glob, joints, h, joints[ARMS[h][3]] + np.array([0.0, 0.0, depth]))
                glob, joints = skel.forward(pose.local, pose.pelvis)
                again = self._carried(glob, joints)
                if again is not None:
                    self.rot, self.pos = again
            letting_go = all(hd.phase != "holding" or hd.off + 1 >= OFF_FRAMES for hd in self.hands)
            holding = [hd for hd in self.hands if hd.phase == "holding"]
            # frames until every holding hand lets go, when all their flags are off
            left = max(OFF_FRAMES - min(max(hd.off for hd in holding), OFF_FRAMES), 1) \
                if all(hd.off > 0 for hd in holding) else None
            touching = self.lifted and tilted and depth > 0.0
            setting_down = sinking or touching or left is not None
            if setting_down and self._level_near_support(both, left) and not both:
                h = 1 if self.hands[1].phase == "holding" else 0
                self._turn_onto_grasp(h, pose.local, glob, model_wrist[h])
                glob, joints = skel.forward(pose.local, pose.pelvis)
            if left is not None:
                # letting go just above the support: put it down by the frame they let go
                bottom, floor = self._floor()
                above = bottom - floor
                if 0.0 < above <= PLACE_HEIGHT:
                    down = min(above / left, self._budget(was))
                    for h in range(2):
                        if self.hands[h].phase == "holding":
                            self.hands[h].correction[2] -= down
                            arm_ik(pose.local, glob, joints, h, joints[ARMS[h][3]] - np.array([0.0, 0.0, down]))
                    glob, joints = skel.forward(pose.local, pose.pelvis)
                    again = self._carried(glob, joints)
                    if again is not None:
                        self.rot, self.pos = again
                    if letting_go:  # what the arm could not lower slips onto the support
                        bottom, floor = self._floor()
                        p = self.pos.copy()
                        p[2] -= min(max(bottom - floor, 0.0), 0.5 * MAX_SPEED * self.dt, self._budget(was))
                        self.pos = p
                    self.events["place_frames"] += 1
            if both:
                # two hands: each to its own grip on the mean pose (the offset joins its correction)
                for h in range(2):
                    hand = self.hands[h]
                    target = self._wrist_of(h)
                    hand.correction = hand.correction + (target - joints[ARMS[h][3]])
                    arm_ik(pose.local, glob, joints, h, target)
                glob, joints = skel.forward(pose.local, pose.pelvis)
                # ... and turned onto its grasp of it
                for h in range(2):
                    self._turn_onto_grasp(h, pose.local, glob, model_wrist[h])
                glob, joints = skel.forward(pose.local, pose.pelvis)
            self._set_down_on_table(above_before)
        else:
            self.pressing = False
            self._settle()

        for h in range(2):
            last = self.hands[1 - h].phase != "holding"
            if self.hands[h].phase == "holding" and self.hands[h].off >= OFF_FRAMES:
                fall = self._fall_height()
                if last and fall > PLACE_HEIGHT:  # kept: let go it would fall to the floor
                    self.events["kept"] += 1
                    continue
                if last and self.hands[h].put_down < PUT_DOWN_FRAMES and fall > LANDED:
                    self.hands[h].put_down += 1  # holds on, putting it down
                    self.events["put_down_frames"] += 1
                    continue
                self.hands[h].phase = "free"
                self.released = True
                self.events["release"] += 1
                if self.hands[1 - h].phase == "holding":
                    self._capture(1 - h, glob, joints)
                    self.events["recapture"] += 1
        for h in range(2):
            hand = self.hands[h]
            if hand.phase == "reaching" and hand.reach.frame >= hand.reach.frames:
                wrist = joints[ARMS[h][3]]
                if _norm(wrist - aimed[h]) <= REACH_MISS:
                    centre = self.shape.centre_at(self.rot, self.pos)
                    off = hand_gap(self.shape, self.rot.T, wrist - centre, hand_offsets(joints, h))
                    reach = None
                    if not hand.reach.again and off >= GRIP_GAP + REGRIP:
                        reach = self._reach(h, pose.wrist_to_object[h], joints, wrist - hand.correction, wrist,
                                            skel.arm_length(h), True)
                    if reach is not None:
                        hand.reach = reach
                        self.events["reaim"] += 1
                    else:
                        self._capture(h, glob, joints)
                else:
                    hand.phase = "free"
                    self.events["reach_missed"] += 1
                hand.reach = None if hand.phase != "reaching" else hand.reach

        # Last: no rule above moves the legs, so ``joints`` still has the model's feet.
        if self.feet is not None:
            self.feet.apply(pose.local, glob, joints)
        self._write(pose, joints)

    def finish(self, skel: Skeleton, pose: Pose) -> None:
        if any(h.phase == "holding" for h in self.hands):
            return
        tipped = self._tip(math.inf)
        bottom, floor = self._floor()
        if bottom != floor or tipped:
            self.pos = self.pos + np.array([0.0, 0.0, floor - bottom])
            self.fall = 0.0
            self.events["landed_at_finish"] += 1
            self._write(pose, skel.forward(pose.local, pose.pelvis)[1])

    def _write(self, pose: Pose, joints: np.ndarray) -> None:
        pose.object_rotation = self.rot.copy()
        pose.object_translation = self.pos.copy()
        pose.object_centre = self.shape.centre_at(self.rot, self.pos)
        pose.wrist_to_object = np.stack([joints[ARMS[h][3]] - pose.object_centre for h in range(2)])
        pose.contact = np.array(self.holding()) | np.array(self.carried_by)

    def _budget(self, was: np.ndarray) -> float:
        """How much farther the object may move this frame: MAX_SPEED from ``was``."""
        return max(MAX_SPEED * self.dt - _norm(self.pos - was), 0.0)

    def _carried(self, glob: np.ndarray, joints: np.ndarray):
        carried = [(glob[ARMS[h][3]] @ hand.rel_rot, joints[ARMS[h][3]] + glob[ARMS[h][3]] @ hand.rel_pos)
                   if hand.phase == "holding" else None for h, hand in enumerate(self.hands)]
        a, b = carried
        if a is not None and b is not None:
            self.events["two_hand_frames"] += 1
            return blend_rotations(a[0], b[0]), (a[1] + b[1]) * 0.5
        return a if a is not None else b

    def _capture(self, h: int, glob: np.ndarray, joints: np.ndarray) -> None:
        gt = glob[ARMS[h][3]].T
        hand = self.hands[h]
        hand.rel_rot = gt @ self.rot
        hand.rel_pos = gt @ (self.pos - joints[ARMS[h][3]])
        hand.phase, hand.reach = "holding", None
        self.lifted = False
        self.events["capture"] += 1

    def _set_down_on_table(self, above_before: bool) -> None:
        bottom = self.shape.bottom_at(self.rot, self.pos)
        if bottom > self.table.height + LIFT_CLEAR:
            self.lifted = True
        over = self.table.over(self.shape.centre_at(self.rot, self.pos))
        if self.lifted and not above_before and bottom < self.table.height and over:
            self.events["not_set_down_from_below"] += 1
        down = self.lifted and above_before and bottom < self.table.height and over
        self.pressing = down and leans(self.rot)  # still off its face: held up while levelled
        if self.pressing:
            self.events["not_set_down_tilted"] += 1
        if not down or self.pressing:
            return
        self.pos = self.pos + np.array([0.0, 0.0, self.table.height - bottom])
        self.lifted = False
        self.released = True
        self.events["set_down"] += 1
        for hand in self.hands:
            if hand.phase == "holding":
                hand.phase, hand.latched = "free", True

    def _settle(self) -> None:
        bottom, floor = self._floor()
        p = self.pos.copy()
        if bottom > floor + LANDED:
            self.events["fall_frames"] += 1
            self.fall = min(self.fall + GRAVITY * self.dt, MAX_SPEED)
            p[2] -= min(self.fall * self.dt, bottom - floor)
            self.pos = p
        else:
            self.fall = 0.0
            if bottom < floor:
                self.events["rise_frames"] += 1
            p[2] += min(FADE_SPEED * self.dt, floor - bottom)
            self.pos = p
            self._tip(TIP_SPEED * self.dt)

    def _tip(self, step: float) -> bool:
        """``ContactStage::tip``: a released object, once resting, turns toward its box face below."""
        face = face_toward(self.rot, lowest_axis(self.rot)) if self.released else None
        if face is None:
            return False
        axis, tilt = face
        bottom = self.shape.bottom_at(self.rot, self.pos)
        self.rot = axis_angle(axis, min(tilt, step)) @ self.rot
        p = self.pos.copy()
        p[2] += bottom - self.shape.bottom_at(self.rot, self.pos)
        self.pos = p
        self.events["tip_frames"] += 1
        return True

    def _reach(self, h: int, model: np.ndarray, joints: np.ndarray, wrist: np.ndarray, start: np.ndarray,
               arm: float, again: bool) -> _Reach | None:
        """``ContactStage::reach``."""
        here = joints[ARMS[h][3]]
        grip = grip_offset(model, self.shape, self.rot, here, self.pos, hand_offsets(joints, h))
        target = self.shape.point_at(self.rot, self.pos, grip)
        if needed_bow(joints, h, target, REACH_LIMIT * arm) is None:
            return None
        gap = _norm(target - start)
        frames = min(max(math.ceil(gap / (REACH_SPEED * self.dt)), MIN_REACH_FRAMES), MAX_REACH_FRAMES)
        return _Reach(0, frames, start - wrist, self.bow, grip, again)

    def _level_near_support(self, both: bool, left: int | None) -> bool:
        """``ContactStage::level_near_support``."""
        bottom, floor = self._floor()
        base = self.base if (self.rot @ self.base)[2] < 0.0 else lowest_axis(self.rot)
        face = face_toward(self.rot, base)
        if face is None:
            return False
        axis, tilt = face
        above = max(bottom - floor, 0.0)
        if left is not None and above <= PLACE_HEIGHT:  # all the way by the frame the hands let go
            allowed, frames = 0.0, float(left)
        else:
            allowed, frames = math.pi / 2 * above / LEVEL_HEIGHT, math.inf
        if not tilt > allowed:
            return False
        if both:
            pivot = (self._wrist_of(0) + self._wrist_of(1)) * 0.5
        else:
            pivot = self._wrist_of(0 if self.hands[0].phase == "holding" else 1)
        q = axis_angle(axis, min(tilt - allowed, max(LEVEL_SPEED * self.dt, (tilt - allowed) / frames)))
        self.rot = q @ self.rot
        self.pos = pivot + q @ (self.pos - pivot)
        self.events["level_frames"] += 1
        return True

    def _turn_onto_grasp(self, h: int, local: np.ndarray, glob: np.ndarray, model_wrist: np.ndarray) -> None:
        """``ContactStage::turn_onto_grasp``."""
        w = ARMS[h][3]
        grasp = self.rot @ self.hands[h].rel_rot.T
        self.hands[h].turn = grasp @ model_wrist.T
        local[w] = local[w] @ (glob[w].T @ grasp)

    def _wrist_of(self, h: int) -> np.ndarray:
        hand = self.hands[h]
        return self.pos + self.rot @ (hand.rel_rot.T @ -hand.rel_pos)

    def _limit_speed(self, skel: Skeleton, pose: Pose, glob: np.ndarray, joints: np.ndarray):
        """``ContactStage::limit_speed``; returns the (new) FK."""
        prev = self.limited
        if prev is not None:
            step = MAX_SPEED * self.dt

            def moved(glob, joints) -> float:
                far = max(_norm(joints[j] - p) for j, p in zip(LIMITED, prev.joints))
                for h in range(2):
                    if self.hands[h].phase == "holding":
                        w = ARMS[h][3]
                        far = max(far, _norm(self._held_centre(h, glob[w], joints[w])
                                             - self._held_centre(h, prev.wrists[h], prev.joints[h])))
                return far

            local, pelvis = pose.local.copy(), pose.pelvis.copy()
            alpha, far, tries = 1.0, moved(glob, joints), 0
            while far > step:
                if tries == LIMIT_TRIES:
                    pose.local, pose.pelvis = prev.local.copy(), prev.pelvis.copy()
                    glob, joints = skel.forward(pose.local, pose.pelvis)
                    break
                tries += 1
                alpha *= 0.98 * step / far
                pose.local = np.stack([nlerp(prev.local[j], local[j], alpha) for j in range(len(local))])
                pose.pelvis = prev.pelvis + (pelvis - prev.pelvis) * alpha
                glob, joints = skel.forward(pose.local, pose.pelvis)
                far = moved(glob, joints)
            if tries:
                self.events["speed_limited"] += 1
        self.limited = _Limited(pose.local.copy(), pose.pelvis.copy(), joints[list(LIMITED)].copy(),
                                [glob[arm[3]].copy() for arm in ARMS])
        return glob, joints

    def _held_centre(self, h: int, rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
        hand = self.hands[h]
        return pos + rot @ (hand.rel_pos + hand.rel_rot @ self.shape.centre)

    def _fall_height(self) -> float:
        bottom, floor = self._floor()
        return bottom - floor

    def _floor(self) -> tuple[float, float]:
        bottom = self.shape.bottom_at(self.rot, self.pos)
        on_table = self.table.over(self.shape.centre_at(self.rot, self.pos)) and bottom >= self.table.height - SUPPORT_DEPTH
        return bottom, self.table.height if on_table else GROUND_Z


def bow_axis(joints: np.ndarray, target: np.ndarray) -> np.ndarray:
    d = target - joints[SPINE[0]]
    a = np.array([-d[1], d[0], 0.0])
    n = _norm(a)
    return a / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])


def needed_bow(joints: np.ndarray, h: int, target: np.ndarray, reach: float):
    axis = bow_axis(joints, target)
    shoulder = ARMS[h][1]

    def gap(bow: float) -> float:
        r = axis_angle(axis, bow / len(SPINE))
        p, turn = joints[SPINE[0]].copy(), IDENTITY
        for k, j in enumerate(SPINE):
            turn = r @ turn
            nxt = joints[SPINE[k + 1]] if k + 1 < len(SPINE) else joints[shoulder]
            p = p + turn @ (nxt - joints[j])
        return _norm(target - p)

    if gap(0.0) <= reach:
        return 0.0, axis
    if gap(MAX_BOW) > reach:
        return None
    lo, hi = 0.0, MAX_BOW
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        if gap(mid) <= reach:
            hi = mid
        else:
            lo = mid
    return hi, axis


@functools.cache
def _catalogue_shape(name: str) -> ObjectShape:
    from .export.bundle import OBJECT_MAX_EDGE, object_mesh_obj
    from .objects.catalogue import CATALOGUE

    spec = CATALOGUE[name]
    lo, hi = spec.shape.mesh().bounds
    return ObjectShape.of((lo + hi) / 2.0, spec.half_extents,
                          surface_from_mesh(*read_obj(object_mesh_obj(name, OBJECT_MAX_EDGE))))


def hand_offsets(joints: np.ndarray, h: int) -> np.ndarray:
    """The wrist's and the 15 finger joints' offsets from hand ``h``'s wrist (world)."""
    w = ARMS[h][3]
    return np.stack([joints[w if k == 0 else HAND_FIRST[h] + k - 1] - joints[w] for k in range(16)])


def hand_gap(shape: ObjectShape, rt: np.ndarray, wrist: np.ndarray, hand: np.ndarray) -> float:
    """``contact::hand_gap``: the nearest hand joint's distance to the object."""
    return float(shape.distance((wrist + hand) @ rt.T).min())


def grip_offset(model: np.ndarray, shape: ObjectShape, rot: np.ndarray, wrist: np.ndarray, pos: np.ndarray,
                hand: np.ndarray) -> np.ndarray:
    """``contact::grip_offset``: the grasp's wrist offset from the object centre (object frame)."""
    centre = shape.centre_at(rot, pos)
    v = np.asarray(model, np.float64).copy()
    valid = bool(_norm(v) > 1e-6 and np.isfinite(v).all())
    if not valid:
        v = wrist - centre
    v[2] = max(v[2], 0.0)
    n = _norm(v)
    direction = v / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])
    rt = rot.T
    hi = _norm(shape.half_extents) + GRIP_MARGIN
    whole = first_touch(shape, rt, direction, hand, hi)
    if not valid:
        return rt @ (direction * whole)
    palm = first_touch(shape, rt, direction, hand[list(PALM)], hi)
    return rt @ (direction * min(max(n, palm), whole))


def first_touch(shape: ObjectShape, rt: np.ndarray, direction: np.ndarray, hand: np.ndarray, hi: float) -> float:
    """``contact::first_touch``: the wrist's distance from the centre along ``direction`` where
    one of ``hand``'s joints first comes within GRIP_GAP of the object, coming in from ``hi``."""
    def gap(length: float) -> float:
        return hand_gap(shape, rt, direction * length, hand)

    lo, up = 0.0, hi
    if gap(hi) >= GRIP_GAP:
        for k in reversed(range(GRIP_SCAN_STEPS)):  # from outside in: the first touch
            length = hi * k / GRIP_SCAN_STEPS
            if gap(length) < GRIP_GAP:
                lo = length
                break
            up = length
        for _ in range(GRIP_SEARCH_STEPS):
            mid = 0.5 * (lo + up)
            if gap(mid) >= GRIP_GAP:
                up = mid
            else:
                lo = mid
    return up


def lowest_axis(r: np.ndarray) -> np.ndarray:
    """The object-frame box axis that ``r`` points most downward."""
    k = 0
    for i in range(1, 3):
        if abs(r[2, i]) > abs(r[2, k]):
            k = i
    a = np.zeros(3)
    a[k] = -1.0 if r[2, k] > 0.0 else 1.0
    return a


def leans(r: np.ndarray) -> bool:
    """``leans``: more than SET_DOWN_TILT off the box face nearest below (it would tip)."""
    face = face_toward(r, lowest_axis(r))
    return face is not None and face[1] > SET_DOWN_TILT


def face_toward(r: np.ndarray, local: np.ndarray):
    """(horizontal unit axis, angle) turning ``r @ local`` onto straight down; None near down/up."""
    down = r @ local
    tilt = math.acos(min(max(-down[2], -1.0), 1.0))
    axis = np.cross(down, np.array([0.0, 0.0, -1.0]))
    n = _norm(axis)
    return (axis / n, tilt) if tilt > 1e-6 and n > 1e-9 else None


def rotation_angle(r: np.ndarray) -> float:
    """The angle of rotation ``r`` (radians, 0 to pi)."""
    q = matrix_to_quaternion(r)
    return 2.0 * math.atan2(_norm(q[:3]), abs(q[3]))


def fade_rotation(r: np.ndarray, step: float) -> np.ndarray:
    """``r`` turned back toward the identity by at most ``step`` radians."""
    if np.array_equal(r, IDENTITY):
        return IDENTITY.copy()
    q = matrix_to_quaternion(r)
    v = _norm(q[:3])
    angle = 2.0 * math.atan2(v, abs(q[3]))
    if angle <= step or v <= 1e-12:
        return IDENTITY.copy()
    sign = -1.0 if q[3] < 0.0 else 1.0
    return axis_angle(sign * q[:3] / v, angle - step)


def nlerp(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    qa, qb = matrix_to_quaternion(a), matrix_to_quaternion(b)
    q = qa * (1.0 - t) + (-1.0 if float(qa @ qb) < 0.0 else 1.0) * qb * t
    n = _norm(q)
    return quaternion_to_matrix(q / n) if n > 1e-12 else a


def blend_rotations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return nlerp(a, b, 0.5)


def arm_ik(local: np.ndarray, glob: np.ndarray, joints: np.ndarray, h: int, target: np.ndarray) -> None:
    """Two-bone IK on arm ``h`` (``contact::arm_ik``); rewrites ``local`` in place."""
    limb_ik(local, glob, joints, ARMS[h], target, glob[ARMS[h][3]])


def limb_ik(local: np.ndarray, glob: np.ndarray, joints: np.ndarray, limb, target: np.ndarray,
            end: np.ndarray) -> None:
    """Two-bone IK on ``limb`` = (parent, root, middle, end) with the end's global rotation
    ``end`` (``skeleton::limb_ik``); rewrites ``local`` in place."""
    c, s, e, w = limb
    ps, pe, pw = joints[s], joints[e], joints[w]
    u, f = pe - ps, pw - pe
    a, b = _norm(u), _norm(f)
    if not (a > 1e-6 and b > 1e-6 and np.isfinite(target).all()):
        return
    lo, hi = abs(a - b) + 1e-4, (a + b) * 0.999
    d = min(max(_norm(target - ps), lo), hi)
    axis = np.cross(u, f)
    n = _norm(axis)
    if n > 1e-9 * a * b:
        axis = axis / n
    else:
        t = np.cross(u, target - ps)
        axis = t / _norm(t) if _norm(t) > 1e-9 else orthogonal(u / a)
    beta = math.atan2(_norm(np.cross(u, f)), float(u @ f))
    cos_new = min(max((d * d - a * a - b * b) / (2.0 * a * b), -1.0), 1.0)
    bend = axis_angle(axis, math.acos(cos_new) - beta)
    end1 = pe + bend @ f
    swing = rotation_between(end1 - ps, target - ps)
    gs = swing @ glob[s]
    ge = swing @ (bend @ glob[e])
    local[s] = glob[c].T @ gs
    local[e] = gs.T @ ge
    local[w] = ge.T @ end


def grasp_onset(skel: Skeleton, x: np.ndarray) -> np.ndarray | None:
    """Where the model's hand first closes on the object (``contact::GraspOnset``): at the
    first of the first PLACE_LOOKAHEAD raw frames in which a hand's flag has been on for
    ON_FRAMES frames, its FK wrist minus its wrist-to-object vector (the mean of both hands
    when both start then); None when no hand starts a grasp that early."""
    on = [0, 0]
    for t in range(min(len(x), PLACE_LOOKAHEAD)):
        pose = Pose.from_features(x[t])
        starts = []
        for h in range(2):
            on[h] = on[h] + 1 if pose.contact[h] else 0
            if on[h] == ON_FRAMES:
                starts.append(h)
        if starts:
            _, joints = skel.forward(pose.local, pose.pelvis)
            return sum(joints[ARMS[h][3]] - pose.wrist_to_object[h] for h in starts) / len(starts)
    return None


def apply_contact_stage(x: np.ndarray, rest_joints: np.ndarray, fps: float, shape: ObjectShape,
                        events: Counter | None = None, place: bool = True, feet: bool = True) -> np.ndarray:
    """A whole de-normalized (T, 335) motion through the stage, frame by frame as the engine
    streams it (the last frame finished); returns the consistent motion as (T, 335) float32.
    ``place``: the resting object starts where the first grasp closes (``grasp_onset``), as
    the engine's streams do unless told not to; ``feet``: planted feet (likewise).
    ``events``, when given, is updated with how often each rule fired (``placed`` when the
    object was moved)."""
    skel, stage = Skeleton(rest_joints), ContactStage(shape, fps, feet)
    x = np.asarray(x)
    centre = grasp_onset(skel, x) if place else None
    if centre is not None:
        stage.events["placed"] += 1
    out = np.empty((len(x), FRAME_DIM), np.float32)
    for t in range(len(x)):
        pose = Pose.from_features(x[t])
        stage.ground(skel, pose)
        if t == 0 and centre is not None:
            stage.place(pose, centre)
        stage.apply(skel, pose)
        if t + 1 == len(x):
            stage.finish(skel, pose)
        out[t] = pose.to_features()
    if events is not None:
        events.update(stage.events)
    return out


def features_from_engine(frames: dict) -> np.ndarray:
    """The engine's frames (``comgrasp generate --out motion.npz``, native coordinates;
    quaternions x, y, z, w) as de-normalized (T, 335) features; contact channels carry
    ``contact_probability``."""
    def rot6d(q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, np.float64)
        x, y, z, w = np.moveaxis(q, -1, 0)
        rows = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                         2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1)
        return rows

    T = len(frames["root_translation"])
    out = np.zeros((T, FRAME_DIM))
    out[:, 0:6] = rot6d(frames["root_rotation"])
    groups = (("body_rotations", range(1, 22)), ("left_hand_rotations", range(25, 40)),
              ("right_hand_rotations", range(40, 55)))
    for key, joints in groups:
        six = rot6d(frames[key])
        for k, j in enumerate(joints):
            out[:, ROT6D_JOINT_COLUMNS[j]:ROT6D_JOINT_COLUMNS[j] + 6] = six[:, k]
    out[:, FIELD["root_transl"].slice] = frames["root_translation"]
    out[:, FIELD["object_rot6d"].slice] = rot6d(frames["object_rotation"])
    out[:, FIELD["object_transl"].slice] = frames["object_translation"]
    out[:, FIELD["object_centre"].slice] = frames["object_centre"]
    out[:, FIELD["lwrist_to_object"].slice] = frames["left_wrist_to_object"]
    out[:, FIELD["rwrist_to_object"].slice] = frames["right_wrist_to_object"]
    out[:, list(CONTACT_CHANNELS)] = frames["contact_probability"]
    return out.astype(np.float32)


__all__ = ["ContactStage", "ObjectShape", "Pose", "Skeleton", "Table", "apply_contact_stage", "arm_ik", "grasp_onset",
           "features_from_engine"]
