"""The SynthGrasp intents: what the hands and the object do in each.

Intents (GRAB's motion_intent names): lift, pass (one hand hands over to the other, which
puts it down), offhand (held out forward at arm's length, as when offering it), inspect
(brought before the face and turned), drink (to the mouth, tilted), pour (tilted over a
spot on the table). Each builds a plan: place the object on the table within reach, grasp
it, key the object through the manipulation (durations at a per-sequence tempo), put it
down on the table and let go.
"""

from __future__ import annotations

import numpy as np

from ..objects.catalogue import TABLE_SIZE, ObjectSpec
from .grasp import Obstacles, edge_point, floor_plane
from .hand_placement import first_grasp, grasp_styles, turn
from .ik import axis_angle, unit
from .plan import IDLE, MAX_SECONDS, HandPlan, Plan, PlanRejected, PoseTrack, Track, grasp_in, grasp_out, snap, world_pose
from .scene import SIDES, THETA_MAX, UP, Scene, make_scene, side_sign
from .subjects import SubjectModel


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

    def reachable(self, side: str, wrist: np.ndarray, obj_pose, margin: float = 0.1) -> bool:
        """``wrist`` is within reach with a bow short of the deepest, and still in front of
        the shoulder (a bow over a spot close to the body would reach back for it)."""
        sc = self.scene
        psi = sc.psi_toward(obj_pose[1])
        theta = sc.required_bend(side, wrist[None], np.array([psi]))[0]
        shoulder = sc.torso(theta, psi).point(sc.rest, sc.arms[side].shoulder)
        return bool(theta <= THETA_MAX - margin and wrist[1] >= shoulder[1])

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
        return sc.pelvis[0] + x, sc.near_edge + self.u(0.08, 0.32)

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

    def table_grasps(self, sides: tuple[str, ...], where: str):
        """Place the object on the table and grasp it with ``sides``; retried with other
        draws until every grasp is found and in reach."""
        sc, obj = self.scene, self.obj
        for _ in range(12):
            base = {s: {"side": unit(np.array([side_sign(s), -0.35 if where == "centre" else -1.0, 0.0])),
                        "top": unit(np.array([0.3 * side_sign(s), 1.0, 0.0]))} for s in sides}
            if obj.handle is not None:  # turn the handle toward the (single) hand
                yaw = np.arctan2(base[sides[0]]["side"][1], base[sides[0]]["side"][0]) + self.u(-0.3, 0.3)
            elif len(sides) == 2:  # faces toward both hands
                yaw = self.u(-0.25, 0.25)
            else:
                yaw = self.u(0.0, 2 * np.pi)
            pose = sc.on_table(obj, *self.table_spot(where), yaw)
            if not all(self.reachable(s, pose[1], pose, margin=0.0) for s in sides):  # cheap first test
                continue
            table = floor_plane(*pose, sc.table_height)
            obstacles = Obstacles((table,))
            grasps = {}
            styles = ["side"] if len(sides) == 2 else grasp_styles(obj, self.rng)  # two hands: at the sides
            for s in sides:
                g = first_grasp(sc, s, obj, self.plan.shape_verts, pose, self.rng, base[s],
                                0.15 if where == "centre" else 0.4, obstacles, sc.table_height,
                                obj.handle is not None, styles)
                if g is None or not self.reachable(s, world_pose(pose, g)[1], pose):
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
        """One hand (or both together) grasps, ``manipulate`` keys the object, they let go."""
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
        ends = [grasp_out(self.plan.hands[s], t + (self.d(0.0, 0.1) if i else 0.0), pose_end, self.rng, self.tempo)
                for i, s in enumerate(sides)]
        self.finish(max(ends))

    def passing(self) -> None:
        """The giver picks it up and brings it before the chest, the taker grips it there,
        the giver lets go and the taker puts it down on its own side."""
        giver, taker = self.mode.split(">")
        sc, obj, u = self.scene, self.obj, self.u
        pose0, grasps = self.table_grasps((giver,), giver)
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
        # The taker's palm goes on the far side from the giver's, or on the taker's side-back.
        g_giver = grasps[giver]
        far = r_pass @ g_giver.approach
        if abs(far[2]) > 0.5:
            far = np.array([side_sign(taker), -0.6, 0.0])
        base = {"side": unit(far * np.array([1.0, 1.0, 0.0])),
                "top": unit(np.array([0.3 * side_sign(taker), 1.0, 0.0]))}
        styles = ["side", "top"] if self.rng.random() < 0.5 else ["top", "side"]
        bottom = p_pass[2] - obj.half_height  # the taker puts it down: its hand stays above
        obstacles = g_giver.obstacles((floor_plane(r_pass, p_pass, bottom),))
        for around in (0.0, np.pi / 3, -np.pi / 3, 2 * np.pi / 3, -2 * np.pi / 3):  # where the giver leaves room
            g_taker = first_grasp(sc, taker, obj, self.plan.shape_verts, (r_pass, p_pass), self.rng,
                                  {k: turn(v, around) for k, v in base.items()}, 0.3, obstacles, bottom, False,
                                  styles, tries=2)
            if g_taker is not None and self.reachable(taker, world_pose((r_pass, p_pass), g_taker)[1],
                                                      (r_pass, p_pass)):
                break
        else:
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
            if self.reachable(taker, world_pose(drop, g_taker)[1], drop):
                break
        else:
            raise PlanRejected(f"cannot put {obj.name} down with the {taker} hand")
        t = self.lower(t, drop)[0] + self.d(0.05, 0.15)
        self.plan.look.key(t, 1.0)
        self.finish(max(end_giver, grasp_out(self.plan.hands[taker], t, drop, self.rng, self.tempo)))

    def finish(self, t: float) -> None:
        """Both arms hang from ``t`` on; the sequence ends a moment later."""
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
        tilt = axis_angle(turn(np.array([1.0, 0.0, 0.0]), u(0, 2 * np.pi)), u(0.0, 0.12))
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
        direction = turn(np.array([0.0, 1.0, 0.0]), u(-0.2, 0.2))
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
            spin = axis_angle(axes[k], self.rng.choice([-1.0, 1.0]) * u(*ranges[k]))
            t = self.key(t + self.d(0.6, 1.0), spin @ r_face, pivot + spin @ (p_face - pivot) + u(-0.02, 0.02, 3))
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


def make_plan(model: SubjectModel, obj: ObjectSpec, verts: np.ndarray, intent: str, mode: str,
              rng: np.random.Generator) -> Plan:
    """Sample a scene and plan one sequence; raises PlanRejected when this draw fails."""
    b = _Builder(make_scene(model, rng), obj, verts, intent, mode, rng)
    if intent == "pass":
        b.passing()
    else:
        b.one_or_both(getattr(b, intent))
    return b.plan
