"""From a plan to per-frame motion: torso, arm IK, fingers, gaze, FK, attached object, contact.

Order per sequence (all frames at once):
1. sample the object track and every hand's wrist target where it is a world pose or held
   (held = object pose x grasp transform);
2. torso yaw toward the object and the forward bow (hip hinge + spine) that keeps those
   targets within reach;
3. the hanging (idle) wrist poses follow the shoulders; reach/retract blend between them and
   the task targets, rising before moving out and lifted wherever the hand would touch the
   table;
4. two-bone IK for both arms, finger curls, head look-at; FK of the whole skeleton;
5. while a hand holds, the object pose is recomputed from that hand's FK wrist and the grasp
   transform (the first-gripping hand carries it when both hold); the plan is rejected
   unless every holding wrist is exactly where the object needs it (< 0.1 mm);
6. GRAB contact codes for the holding frames, from each grasp's object-frame codes.

The legs keep their rest pose in the world (the hip hinge turns the pelvis about the line
through both hip joints and the hips counter-rotate), so the feet neither slide nor leave
the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import skeleton as sk
from ..objects.catalogue import TABLE_SIZE
from .ik import HEAD, LEFT_HIP, NECK, RIGHT_HIP, SPINE, arm_ik, look_at, matrix_to_rotvec, minjerk, slerp
from .plan import FPS, HELD, IDLE, Plan, PlanRejected, Track, segments, world_pose
from .scene import SIDES

THETA_MARGIN = 0.03  # extra bow (rad) beyond the smallest one that reaches
LAG = 0.4  # share of a reach during which the hand only rises (retracting: only lowers)
ARC = 0.06  # m the hand's path rises above the straight line midway through reaching out
TABLE_CLEARANCE = 0.01  # m a reaching hand keeps above the table top
TOLERANCE = 1e-4  # m: a holding wrist must be this close to where the object needs it
BODY_TOLERANCE = 0.01  # m the carried object may press into the body proxy (e.g. a wrist)


@dataclass
class Motion:
    """One synthesized sequence, everything per frame (T = frames at 120 fps)."""

    local_rot: np.ndarray  # (T, 55, 3, 3) local joint rotations
    transl: np.ndarray  # (T, 3) SMPL-X transl (pelvis = rest J0 + transl)
    global_rot: np.ndarray  # (T, 55, 3, 3) from FK
    joints: np.ndarray  # (T, 55, 3) from FK
    object_rot: np.ndarray  # (T, 3, 3) column-vector world rotation
    object_pos: np.ndarray  # (T, 3)
    holding: np.ndarray  # (T, 2) bool, [left, right]
    contact_object: np.ndarray  # (T, V) int8 GRAB codes
    contact_body: np.ndarray  # (T, P) int8 GRAB codes on the subject's proxy points

    @property
    def n_frames(self) -> int:
        return int(self.transl.shape[0])

    @property
    def fullpose(self) -> np.ndarray:
        """(T, 165) axis-angle in GRAB's layout, which is the joint order 0..54."""
        return matrix_to_rotvec(self.local_rot).reshape(self.n_frames, -1)


@dataclass
class _HandFrames:
    """A hand's keys located per frame (segment start/end key, raw fraction, their kinds)
    and its wrist target being filled in."""

    k0: np.ndarray
    k1: np.ndarray
    u: np.ndarray
    kind0: np.ndarray
    kind1: np.ndarray
    key_rot: np.ndarray  # (K, 3, 3), NaN at idle keys
    key_pos: np.ndarray
    rot: np.ndarray  # (T, 3, 3) target, NaN until filled
    pos: np.ndarray

    @property
    def concrete(self) -> np.ndarray:
        """Frames whose target is a world pose (not involving the shoulder-relative idle pose)."""
        return (self.kind0 != IDLE) & ((self.kind1 != IDLE) | (self.u == 0))


def _task_targets(plan: Plan, side: str, t: np.ndarray, obj_rot: np.ndarray, obj_pos: np.ndarray) -> _HandFrames:
    """The wrist targets that do not depend on the torso: free world poses (min-jerk between
    keys) and, while held, object pose x grasp transform."""
    hp = plan.hands[side]
    times, kinds = np.asarray(hp.times), np.asarray(hp.kinds)
    key_rot = np.full((len(times), 3, 3), np.nan)
    key_pos = np.full((len(times), 3), np.nan)
    for k, kind in enumerate(kinds):
        if kind == HELD:
            key_rot[k], key_pos[k] = world_pose(plan.object.at(times[k]), hp.grasp)
        elif kind != IDLE:
            key_rot[k], key_pos[k] = hp.poses[k]
    k0, k1, u = segments(times, t)
    hf = _HandFrames(k0, k1, u, kinds[k0], kinds[k1], key_rot, key_pos,
                     np.full((len(t), 3, 3), np.nan), np.full((len(t), 3), np.nan))
    held = (hf.kind0 == HELD) & (hf.kind1 == HELD)
    free = hf.concrete & ~held
    a = k0[free]
    b = np.where(hf.kind1[free] == IDLE, a, k1[free])
    s = minjerk(u[free])
    hf.rot[free] = slerp(key_rot[a], key_rot[b], s)
    hf.pos[free] = key_pos[a] + s[:, None] * (key_pos[b] - key_pos[a])
    if held.any():
        hf.rot[held] = obj_rot[held] @ hp.grasp.rot
        hf.pos[held] = obj_pos[held] + obj_rot[held] @ hp.grasp.pos
    return hf


def _blend_with_idle(hf: _HandFrames, idle_rot: np.ndarray, idle_pos: np.ndarray) -> np.ndarray:
    """Fill the frames that involve the hanging pose: rest there, or reach out / retract.
    Reaching, the hand rises beside the body before it moves out on an arc (``ARC`` higher
    midway); retracting is the reverse. Returns the frames it filled."""
    still = (hf.kind0 == IDLE) & (hf.kind1 == IDLE)
    hf.rot[still], hf.pos[still] = idle_rot[still], idle_pos[still]
    filled = still.copy()
    for out, m in ((True, (hf.kind0 == IDLE) & (hf.kind1 != IDLE)),
                   (False, (hf.kind0 != IDLE) & (hf.kind1 == IDLE) & (hf.u > 0))):
        if not m.any():
            continue
        u = hf.u[m] if out else 1.0 - hf.u[m]  # 0 at the hanging pose, 1 at the target
        k = hf.k1[m] if out else hf.k0[m]
        s_v, s_h = minjerk(u / (1 - LAG)), minjerk((u - LAG) / (1 - LAG))
        pos = idle_pos[m] + np.stack([s_h, s_h, s_v], axis=-1) * (hf.key_pos[k] - idle_pos[m])
        pos[:, 2] += 4.0 * ARC * s_h * (1.0 - s_h)
        hf.rot[m] = slerp(idle_rot[m], hf.key_rot[k], minjerk(u))
        hf.pos[m] = pos
        filled |= m
    return filled


def _clear_table(hf: _HandFrames, hand, curls: np.ndarray, sc, frames: np.ndarray) -> None:
    """Lift the wrist target wherever a hand capsule would dip into the table top (the lift
    is a max of continuous functions of time, so the path stays continuous)."""
    reach = 0.22  # farther than this from the table top, no part of the hand can touch it
    gap = np.maximum(np.abs(hf.pos[:, :2] - sc.table_centre[:2]) - np.array(TABLE_SIZE[:2]) / 2, 0.0)
    near = (gap.max(axis=1) < reach) & (hf.pos[:, 2] < sc.table_height + reach)
    idx = np.nonzero(frames & near)[0]
    if not len(idx):
        return
    a, b = hand.capsules(curls[idx])
    ends = np.einsum("nij,nkj->nki", hf.rot[idx], np.concatenate([a, b], axis=1)) + hf.pos[idx, None]
    r = np.tile(hand.cap_radius, 2)
    half = np.array(TABLE_SIZE[:2]) / 2 + r[:, None]
    over = (np.abs(ends[..., :2] - sc.table_centre[:2]) < half).all(-1)
    need = np.where(over, sc.table_height + TABLE_CLEARANCE - (ends[..., 2] - r), 0.0).max(axis=1)
    hf.pos[idx, 2] += np.maximum(need, 0.0)


def _spine_track(plan: Plan, hands: dict[str, _HandFrames], values, default: float, t: np.ndarray) -> np.ndarray:
    """Interpolate a torso value keyed at every hand and object key time (``values(frame)``
    where a hand has a world target there, ``default`` elsewhere)."""
    times = sorted({0.0, plan.duration, *plan.object.pos.times, *(x for hp in plan.hands.values() for x in hp.times)})
    track = Track()
    active = np.any([hf.concrete for hf in hands.values()], axis=0)
    for tk in times:
        f = min(int(round(tk * FPS)), len(t) - 1)
        track.key(tk, values(f) if active[f] else default)
    return track.sample(t)


def synthesize(plan: Plan) -> Motion:
    """All frames of a plan (steps 1-6 above); raises PlanRejected if the plan fails a check."""
    sc = plan.scene
    rest = sc.rest
    T = int(round(plan.duration * FPS)) + 1
    t = np.arange(T) / FPS
    obj_rot, obj_pos = plan.object.sample(t)
    hands = {s: _task_targets(plan, s, t, obj_rot, obj_pos) for s in SIDES}

    # Torso: yaw toward the object, then the bow every world target needs.
    psi = _spine_track(plan, hands, lambda f: sc.psi_toward(obj_pos[f]), 0.0, t)
    need = np.zeros(T)
    for s, hf in hands.items():
        c = hf.concrete
        need[c] = np.maximum(need[c], sc.required_bend(s, hf.pos[c], psi[c]) + THETA_MARGIN)
    theta = np.maximum(_spine_track(plan, hands, lambda f: max(sc.theta0, need[f]), sc.theta0, t), need)
    tor = sc.torso(theta, psi)

    local = np.tile(np.eye(3), (T, sk.NUM_JOINTS, 1, 1))
    local[:, 0] = tor.pelvis_rot
    local[:, [LEFT_HIP, RIGHT_HIP]] = tor.hip_local[:, None]
    local[:, list(SPINE)] = tor.local[:, None]
    for s, hf in hands.items():
        curls = plan.hands[s].curls.sample(t)
        _clear_table(hf, sc.hands[s], curls, sc, _blend_with_idle(hf, *sc.idle_pose(s, tor, psi)))
        arm = sc.arms[s]
        l_sh, l_el, l_wr, _ = arm_ik(arm, tor.point(rest, arm.shoulder), tor.rot3, hf.pos, hf.rot,
                                     tor.rot3 @ sc.pole[s])
        local[:, arm.shoulder], local[:, arm.elbow], local[:, arm.wrist] = l_sh, l_el, l_wr
        hand = sc.hands[s]
        local[:, hand.fingers] = hand.finger_locals(curls)
    neck_head = look_at(rest, tor, obj_pos, plan.look.sample(t), plan.pitch.sample(t))
    local[:, NECK] = local[:, HEAD] = neck_head

    transl = tor.pelvis_pos - rest[0]
    g, j = (x.numpy() for x in sk.forward_kinematics(torch.from_numpy(local), torch.from_numpy(rest),
                                                      torch.from_numpy(transl)))

    # The object follows the holding wrist; check that every holding wrist is where it must be.
    holding = np.zeros((T, 2), dtype=bool)
    for i, s in enumerate(SIDES):
        hold = plan.hands[s].hold
        if hold:
            holding[int(round(hold[0] * FPS)): int(round(hold[1] * FPS)) + 1, i] = True
    out_rot, out_pos = obj_rot.copy(), obj_pos.copy()
    for s in reversed(plan.order):
        m = holding[:, SIDES.index(s)]
        gr = plan.hands[s].grasp
        wrist = sc.arms[s].wrist
        out_rot[m] = g[m, wrist] @ gr.rot.T
        out_pos[m] = j[m, wrist] - out_rot[m] @ gr.pos
    for s in plan.order:
        m = holding[:, SIDES.index(s)]
        err = np.linalg.norm(j[m, sc.arms[s].wrist] - hands[s].pos[m], axis=-1).max()
        if err > TOLERANCE:
            raise PlanRejected(f"{s} wrist misses the held object by {err * 1000:.1f} mm")

    _check_body_clear(plan, g, j, out_rot, out_pos, holding)
    contact_object, contact_body = _contacts(plan, holding)
    return Motion(local, transl, g, j, out_rot, out_pos, holding, contact_object, contact_body)


def _check_body_clear(plan: Plan, g: np.ndarray, j: np.ndarray, obj_rot: np.ndarray, obj_pos: np.ndarray,
                      holding: np.ndarray) -> None:
    """Reject the plan if the carried object cuts into the body (arms, torso, head) by more
    than BODY_TOLERANCE: the object's SDF at points along each body capsule's axis, less its
    radius, on every 6th held frame."""
    rest = plan.scene.rest
    a, b, r, joint = plan.scene.model.body_capsules
    f = np.nonzero(holding.any(axis=1))[0][::6]
    along = np.linspace(0.0, 1.0, 6)[:, None]
    axis = a[None] * (1 - along[..., None]) + b[None] * along[..., None]  # (6, K, 3) rest points
    posed = np.einsum("tkij,skj->tski", g[f][:, joint], axis - rest[joint]) + j[f][:, joint][:, None]
    local = np.einsum("tji,tskj->tski", obj_rot[f], posed - obj_pos[f][:, None, None])
    depth = (r - plan.obj.shape.sdf(local)).max()
    if depth > BODY_TOLERANCE:
        raise PlanRejected(f"{plan.obj.name} cuts {depth * 1000:.0f} mm into the body")


def _contacts(plan: Plan, holding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """contact/object: per object vertex the code of the nearest holding-hand point within
    GRAB's threshold; contact/body: each touching hand point's own code. Constant per set
    of holding hands, since a holding hand is rigid relative to the object."""
    T = len(holding)
    n_points = plan.scene.model.proxy.num_points
    c_obj = np.zeros((T, len(plan.shape_verts)), np.int8)
    c_body = np.zeros((T, n_points), np.int8)
    for combo in {tuple(r) for r in holding if r.any()}:
        rows = np.all(holding == combo, axis=1)
        dist = np.full(len(plan.shape_verts), np.inf)
        codes = np.zeros(len(plan.shape_verts), np.int8)
        body = np.zeros(n_points, np.int8)
        for s, on in zip(SIDES, combo):
            if not on:
                continue
            gr = plan.hands[s].grasp
            nearer = gr.object_dist < dist
            codes = np.where(nearer, gr.object_codes, codes)
            dist = np.minimum(dist, gr.object_dist)
            body[gr.hand.index] = gr.body_codes
        c_obj[rows] = codes
        c_body[rows] = body
    return c_obj, c_body
