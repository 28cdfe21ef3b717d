"""Grasps that close on the object's analytic surface.

A grasp is the wrist pose in the object frame plus a curl per finger, found geometrically:
the open hand (fingers straight) is oriented from the grasp type, then slid along its
approach direction until its proxy first touches the object's SDF (or an obstacle: the
table, the other hand), and each finger then curls until its capsules first touch. So the
hand touches the object within ``GAP`` and penetrates nothing. Because the hand is rigid
relative to the object while it holds it, the GRAB contact codes of a grasp are computed
once, in the object frame.

Hand orientation convention (SMPL-X canonical hand, wrist rotation = identity): the palm
faces -y, the fingers point +x (left hand) / -x (right hand), the thumb side is +z.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .. import skeleton as sk
from ..objects.shapes import Shape
from ..surface import LEFT_HAND_CODES, RIGHT_HAND_CODES
from .ik import axis_angle, unit
from .subjects import SubjectModel

# GRAB's contact threshold is a squared distance of 2e-5 m^2 (reference §1.3), about 4.5 mm.
CONTACT_THRESHOLD = float(np.sqrt(2e-5))
GAP = 0.0005  # clearance left between the hand proxy and the object when it touches
PALM_RADIUS = 0.012  # radius of the palm capsules in surface.py
# Maximum flexion (degrees) of joints 1..3 of each finger at curl 1, in sk.FINGERS order.
FLEX_DEG = {"index": (75, 95, 60), "middle": (75, 95, 60), "pinky": (75, 95, 60), "ring": (75, 95, 60),
            "thumb": (45, 45, 60)}
_PALM_NORMAL = np.array([0.0, -1.0, 0.0])


class Hand:
    """One hand of a subject: its proxy points, finger curl model and capsules."""

    def __init__(self, model: SubjectModel, side: str):
        self.side = side
        self.rest = model.rest
        proxy = model.proxy
        idx = {n: i for i, n in enumerate(sk.JOINT_NAMES)}
        self.wrist = idx[f"{side}_wrist"]
        codes = LEFT_HAND_CODES if side == "left" else RIGHT_HAND_CODES
        self.index = np.nonzero(proxy.mask(codes))[0]  # into the subject's proxy points
        self.code = proxy.code[self.index]
        self.fingers = np.array([[idx[f"{side}_{f}{k}"] for k in (1, 2, 3)] for f in sk.FINGERS])
        self.finger_mask = np.stack([np.isin(self.code, f + 1) for f in self.fingers])  # (5, Ph)
        self.axes = np.stack([unit(np.cross(self.rest[f[1]] - self.rest[f[0]], _PALM_NORMAL)) for f in self.fingers])
        self.max_angles = np.radians([FLEX_DEG[f] for f in sk.FINGERS])
        sign = 1.0 if side == "left" else -1.0
        # Columns: finger direction, palm normal, thumb side (canonical).
        self.canonical = np.stack([[sign, 0.0, 0.0], _PALM_NORMAL, [0.0, 0.0, 1.0]], axis=-1)
        caps = [c for c in proxy.capsules if c.code in codes]
        self._cap_a = np.stack([c.a for c in caps])
        self._cap_b = np.stack([c.b for c in caps])
        self.cap_radius = np.array([c.radius for c in caps])
        self._cap_joint = np.array([c.joint for c in caps])
        # Points along each capsule's axis (<= 4 mm apart): the hand as seen by another hand.
        n = [max(2, int(np.ceil(np.linalg.norm(c.b - c.a) / 0.004)) + 1) for c in caps]
        self._axis_cap = np.repeat(np.arange(len(caps)), n)
        self._axis_frac = np.concatenate([np.linspace(0.0, 1.0, k) for k in n])[:, None]
        self.axis_radius = self.cap_radius[self._axis_cap]
        cap_code = np.array([c.code for c in caps])[self._axis_cap]
        self.axis_finger = np.stack([np.isin(cap_code, f + 1) for f in self.fingers])  # (5, M)
        # Points grouped by the joint that carries them: (joint, hand point indices, offsets).
        joint, pts = proxy.joint[self.index], proxy.rest_points[self.index]
        self._groups = [(j, np.nonzero(joint == j)[0], pts[joint == j] - self.rest[j]) for j in np.unique(joint)]
        # Finger FK (``_fk``) walks each finger's 3-joint chain from the wrist directly.
        assert all(sk.PARENTS[f[0]] == self.wrist and sk.PARENTS[f[1]] == f[0] and sk.PARENTS[f[2]] == f[1]
                   for f in self.fingers)
        self._bone = np.stack([self.rest[self.fingers[:, k + 1]] - self.rest[self.fingers[:, k]] for k in (0, 1)])
        self._rest_wrist_frame = self.rest - self.rest[self.wrist]

    def finger_locals(self, curls: np.ndarray) -> np.ndarray:
        """(..., 5) curls in [0, 1] -> (..., 5, 3, 3, 3) local rotations of the finger joints."""
        angles = np.asarray(curls)[..., :, None] * self.max_angles
        return axis_angle(self.axes[:, None, :], angles)

    def _fk(self, curls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global rotations and positions (wrist frame) of all joints for curls (B, 5), every
        joint but the fingers at rest. Only the 5 finger chains move, so they are walked on
        their own (3 steps of (B, 5) products) instead of the whole 55-joint tree: the grasp
        search calls this thousands of times per sequence."""
        curls = np.atleast_2d(curls)
        local = self.finger_locals(curls)  # (B, 5, 3, 3, 3)
        g = np.tile(np.eye(3), (len(curls), sk.NUM_JOINTS, 1, 1))
        j = np.tile(self._rest_wrist_frame, (len(curls), 1, 1))
        g1 = local[:, :, 0]
        g2 = g1 @ local[:, :, 1]
        g[:, self.fingers[:, 0]], g[:, self.fingers[:, 1]], g[:, self.fingers[:, 2]] = g1, g2, g2 @ local[:, :, 2]
        j2 = j[:, self.fingers[:, 0]] + (g1 @ self._bone[0][..., None])[..., 0]
        j[:, self.fingers[:, 1]] = j2
        j[:, self.fingers[:, 2]] = j2 + (g2 @ self._bone[1][..., None])[..., 0]
        return g, j

    def points(self, curls: np.ndarray) -> np.ndarray:
        """Hand proxy points (B, Ph, 3) in the wrist frame (wrist at the origin, rotation
        identity) for curls (B, 5)."""
        g, j = self._fk(curls)
        # surface.pose_points (p = G_j (p_rest - J_j) + J_j), one matrix product per joint.
        pts = np.empty((len(g), len(self.index), 3))
        for jt, sel, offsets in self._groups:
            pts[:, sel] = offsets @ np.swapaxes(g[:, jt], -1, -2) + j[:, jt, None]
        return pts

    def capsules(self, curls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both ends (B, K, 3) of every hand capsule in the wrist frame for curls (B, 5)."""
        g, j = self._fk(curls)
        cj = self._cap_joint
        a = np.einsum("bkij,kj->bki", g[:, cj], self._cap_a - self.rest[cj]) + j[:, cj]
        b = np.einsum("bkij,kj->bki", g[:, cj], self._cap_b - self.rest[cj]) + j[:, cj]
        return a, b

    def axis(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Points (..., M, 3) along the capsule axes, from the capsule ends (..., K, 3)."""
        return a[..., self._axis_cap, :] + self._axis_frac * (b - a)[..., self._axis_cap, :]

    @cached_property
    def open_points(self) -> np.ndarray:
        return self.points(np.zeros(5))[0]

    @cached_property
    def open_axis(self) -> np.ndarray:
        return self.axis(*(x[0] for x in self.capsules(np.zeros(5))))

    def anchor(self, lam: float) -> np.ndarray:
        """A point on the palm surface (wrist frame): ``lam`` of the way from the wrist to the
        middle-finger knuckle (0.5 palm centre, 1 knuckles)."""
        middle1 = self.fingers[sk.FINGERS.index("middle"), 0]
        return lam * (self.rest[middle1] - self.rest[self.wrist]) + PALM_RADIUS * _PALM_NORMAL

    def orientation(self, palm_normal: np.ndarray, thumb: np.ndarray) -> np.ndarray:
        """Wrist rotation that makes the palm face ``palm_normal`` with the thumb side toward
        ``thumb`` (orthogonalized)."""
        n = unit(np.asarray(palm_normal, float))
        t = unit(thumb - (thumb @ n) * n)
        f = np.cross(n, t) if self.side == "right" else np.cross(t, n)
        return np.stack([f, n, t], axis=-1) @ self.canonical.T


@dataclass
class Obstacles:
    """What a grasping hand must not enter besides the object, in the object frame:
    half-spaces ``p . n <= offset`` (a table top) and capsules (the other hand)."""

    planes: tuple[tuple[np.ndarray, float], ...] = ()
    cap_a: np.ndarray | None = None
    cap_b: np.ndarray | None = None
    cap_r: np.ndarray | None = None

    def plane_sdf(self, p: np.ndarray) -> np.ndarray:
        d = np.full(p.shape[:-1], np.inf)
        for n, off in self.planes:
            d = np.minimum(d, p @ n - off)
        return d

    def capsule_sdf(self, p: np.ndarray) -> np.ndarray:
        """Exact near the capsules; farther than 2 cm from their bounding box, the distance
        to the box (a lower bound, which is all sphere tracing needs)."""
        if self.cap_a is None:
            return np.full(p.shape[:-1], np.inf)
        ends = np.concatenate([self.cap_a, self.cap_b])
        lo, hi = ends.min(0) - self.cap_r.max(), ends.max(0) + self.cap_r.max()
        d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=-1)
        near = d < 0.02
        q = p[near]
        ba = self.cap_b - self.cap_a
        inv = 1.0 / (ba * ba).sum(-1)
        exact = np.empty(len(q))
        for i in range(0, len(q), 4096):
            pa = q[i:i + 4096, None, :] - self.cap_a
            h = np.clip(np.einsum("nkj,kj->nk", pa, ba) * inv, 0.0, 1.0)
            diff = pa - h[..., None] * ba
            exact[i:i + 4096] = (np.sqrt(np.einsum("nkj,nkj->nk", diff, diff)) - self.cap_r).min(axis=1)
        d[near] = exact
        return d

    def plane_hit(self, p: np.ndarray, direction: np.ndarray) -> float:
        """How far the points can move along ``direction`` before one comes within GAP of a
        plane (exact, so a hand sliding along the table costs no tracing steps)."""
        s = np.inf
        for n, off in self.planes:
            rate = float(direction @ n)
            if rate < 0:
                s = min(s, float((p @ n - off - GAP).min()) / -rate)
        return s


def floor_plane(obj_rot: np.ndarray, obj_pos: np.ndarray, height: float) -> tuple[np.ndarray, float]:
    """The world half-space below ``height`` (the table top) as an object-frame half-space."""
    return obj_rot[2].copy(), float(height - obj_pos[2])


@dataclass
class Grasp:
    """A hand holding the object; every array is in the object frame."""

    hand: Hand
    rot: np.ndarray  # (3, 3) wrist rotation
    pos: np.ndarray  # (3,) wrist position
    curls: np.ndarray  # (5,)
    approach: np.ndarray  # (3,) direction the hand moved in to touch (into the object)
    points: np.ndarray  # (Ph, 3) hand proxy points
    cap_a: np.ndarray
    cap_b: np.ndarray
    object_dist: np.ndarray  # (V,) distance of each object vertex to the nearest hand point
    object_codes: np.ndarray  # (V,) int8 GRAB code of that point within the threshold, else 0
    body_codes: np.ndarray  # (Ph,) int8 each hand point's own code where it touches, else 0

    def obstacles(self, extra_planes=()) -> Obstacles:
        return Obstacles(tuple(extra_planes), self.cap_a, self.cap_b, self.hand.cap_radius)


def make_grasp(hand: Hand, shape: Shape, verts: np.ndarray, rot: np.ndarray, target: np.ndarray,
               approach: np.ndarray, lam: float, obstacles: Obstacles) -> Grasp | None:
    """Slide the open hand (wrist rotation ``rot``, object frame) along ``approach`` so that
    its palm anchor travels on the line through ``target`` until it first touches, then
    curl each finger until it touches. None if the hand cannot touch the object there.

    Clearance is measured from the hand's surface points to the object and the planes, and
    from its capsule axes (less their radii) to the other hand's capsules (far fewer points).
    """
    approach = unit(approach)

    def clearance(curls, pos, points=slice(None)):  # (B, 5) -> per-point and per-axis-point clearance
        ends = (x @ rot.T + pos for x in hand.capsules(curls))
        pts = hand.points(curls)[:, points] @ rot.T + pos
        return (np.minimum(shape.sdf(pts), obstacles.plane_sdf(pts)),
                obstacles.capsule_sdf(hand.axis(*ends)) - hand.axis_radius)

    pos = target - 0.3 * approach - rot @ hand.anchor(lam)
    pts, axis = hand.open_points @ rot.T + pos, hand.open_axis @ rot.T + pos
    if min(obstacles.plane_sdf(pts).min(), (obstacles.capsule_sdf(axis) - hand.axis_radius).min()) < GAP:
        return None  # starts inside the table or the other hand
    s = min(_trace(lambda s: min(shape.sdf(pts + s * approach).min(),
                                 (obstacles.capsule_sdf(axis + s * approach) - hand.axis_radius).min())),
            obstacles.plane_hit(pts, approach))
    if not np.isfinite(s):
        return None
    pos = pos + s * approach
    curls = _close_fingers(hand, clearance, pos)

    d_pts, d_axis = clearance(curls[None], pos)
    pts = hand.points(curls)[0] @ rot.T + pos
    a, b = (x[0] @ rot.T + pos for x in hand.capsules(curls))
    sdf = shape.sdf(pts)
    if sdf.min() > GAP + 1e-4 or min(d_pts.min(), d_axis.min()) < GAP - 1e-5:
        return None
    dist_v, nearest = cKDTree(pts).query(verts, distance_upper_bound=CONTACT_THRESHOLD)
    touching = np.isfinite(dist_v)
    if not touching.any():
        return None
    object_codes = np.where(touching, hand.code[np.minimum(nearest, len(pts) - 1)], 0).astype(np.int8)
    body_codes = np.where(sdf <= CONTACT_THRESHOLD, hand.code, 0).astype(np.int8)
    return Grasp(hand, rot, pos, curls, approach, pts, a, b, dist_v, object_codes, body_codes)


def _trace(distance, max_travel: float = 0.6) -> float:
    """Sphere tracing: the travel ``s`` at which ``distance(s)`` (a lower bound of the gap
    to everything) comes down to GAP, stepping by the gap so it never overshoots; inf if the
    hand passes by."""
    s = 0.0
    for _ in range(200):
        step = float(distance(s)) - GAP
        if step < 2e-5:
            return s
        s += step
        if s > max_travel:
            return np.inf
    return np.inf


def _close_fingers(hand: Hand, clearance, pos: np.ndarray) -> np.ndarray:
    """Per finger, the largest curl on the way from open at which it still keeps ``GAP``:
    the first touch on a coarse grid of curls, then on a fine grid inside that step (the
    fingers are independent, so every finger is searched in the same batch)."""

    on_finger = hand.finger_mask.any(axis=0)

    def clear(curls):  # (B, 5) -> (B, 5) clearance of each finger
        d_pts, d_axis = clearance(curls, pos, on_finger)
        return np.stack([np.minimum(d_pts[:, m].min(axis=1), d_axis[:, ma].min(axis=1))
                         for m, ma in zip(hand.finger_mask[:, on_finger], hand.axis_finger)], axis=1)

    coarse = np.linspace(0.0, 1.0, 33)
    ok = clear(np.repeat(coarse[:, None], 5, axis=1)) >= GAP
    first = np.where((~ok).any(axis=0), (~ok).argmax(axis=0), len(coarse))  # first touching step
    lo = coarse[np.clip(first - 1, 0, None)]
    fine = lo + np.linspace(0.0, 1.0, 17)[:, None] * (coarse[1] - coarse[0]) * (first > 0) * (first < len(coarse))
    ok = clear(fine) >= GAP
    last = np.where(ok.all(axis=0), len(fine) - 1, ok.argmin(axis=0) - 1)  # last clear fine step
    return np.where(first == 0, 0.0, fine[np.clip(last, 0, None), np.arange(5)])


def edge_point(shape: Shape, origin: np.ndarray, direction: np.ndarray, max_len: float = 0.3) -> np.ndarray:
    """The last point inside the object on the ray from an inside ``origin`` (object frame),
    e.g. the rim of a cup's top toward the mouth."""
    direction = unit(np.asarray(direction, float))
    lo, hi = 0.0, max_len
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if shape.sdf(origin + mid * direction) <= 0.0:
            lo = mid
        else:
            hi = mid
    return origin + lo * direction
