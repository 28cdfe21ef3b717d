"""Does a motion do what its SynthGrasp prompt asks? A rule-based checker.

The prompt is parsed by ``grab.text_parse.parse_prompt`` (intent, named hand(s), object);
``check_motion`` tests a motion (FK joints, object pose, per-hand contact flags) against it.
A hand *holds* in a frame when its contact flag is on and one of its joints (wrist and 15
finger joints) is within ``near_m`` of the object's surface (a flag alone could be on with
the hand far away); it *grasps* when it holds for ``min_hold_s`` in a row.

Rules (thresholds in :class:`CheckConfig`, set from what ``synth.intents`` generates and
measured on SynthGrasp's ground truth, with margins):

* ``grasp``: every named hand grasps ('both' and a pass name two); a single named hand
  holds at least as long as the other hand; with no hand named, some hand grasps.
* ``unheld_still``: while no hand holds, the object moves at most ``still_mm`` / turns at
  most ``still_deg`` from where it was last held (``metrics.unheld_object_motion``).
* ``pass``: the giver grasps first, the taker holds last (unnamed: two different hands).
* ``lift``: while grasped, the object rises ``lift_m`` above its start (generator: 15-30 cm).
* ``drink``: while grasped, the object's surface comes within ``mouth_m`` of the head joint
  (the rim at the mouth; ground truth 8-12 cm, inspect never nearer than 23 cm).
* ``pour``: while grasped, the object's up axis tilts ``pour_deg`` (generator: 46-103 deg).
* ``inspect``: grasped, the object rises ``raise_m``, comes within ``face_m`` of the head
  joint (26-36 cm before the mouth) and turns through ``turn_deg`` while there.
* ``offhand`` (held out at arm's length, as when offering it): in some grasped frame the
  object is at least ``ahead_m`` ahead of and at most ``below_shoulder_m`` below the
  shoulders, with a holding arm straightened to ``reach_frac`` of its length.

The rules are necessary conditions, not a classifier: SynthGrasp's lifts, for instance,
often also pass the offhand rule (both hold the object up at a near-straight arm). Every
sequence of SynthGrasp-400 and -1000 passes (``comgrasp-data check-intent DATA``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import skeleton as sk
from .grab.text_parse import SIDES, UNKNOWN, Intent, parse_prompt
from .metrics import rotation_angle_deg, unheld_object_motion
from .objects.catalogue import CATALOGUE
from .representation import features_to_joints, features_to_params

SYNTH_INTENTS: tuple[str, ...] = ("lift", "pass", "offhand", "inspect", "drink", "pour")  # synth.generate.INTENTS
_HAND_JOINTS = (sk.LEFT_WRIST, *sk.LEFT_HAND_JOINTS, sk.RIGHT_WRIST, *sk.RIGHT_HAND_JOINTS)  # 16 per hand
_ARMS = ((16, 18, sk.LEFT_WRIST), (17, 19, sk.RIGHT_WRIST))  # shoulder, elbow, wrist
_HIPS = (1, 2)  # left, right

__all__ = ["CheckConfig", "CheckResult", "Intent", "MotionTrack", "UNKNOWN", "check_feature_set", "check_features",
           "check_motion", "grasp_offsets", "intent_of", "intent_rates", "parse_prompt", "track_from_engine",
           "track_from_features"]


@dataclass
class MotionTrack:
    """What the checker reads of a motion (world metres, z up)."""

    joints: np.ndarray  # (T, 55, 3) FK joints
    object_rot: np.ndarray  # (T, 3, 3) column convention: v_world = R v_obj + t
    object_transl: np.ndarray  # (T, 3)
    contact: np.ndarray  # (T, 2) bool flags [left, right]
    fps: float
    object_sdf: Callable[[np.ndarray], np.ndarray]  # object-frame points (..., 3) -> signed distance (m)


@dataclass(frozen=True)
class CheckConfig:
    """Thresholds; "GT" is the range over the 400 sequences of SynthGrasp-400 at 30 fps."""

    near_m: float = 0.05  # holding hand's nearest joint to the surface (GT <= 3.1 cm)
    min_hold_s: float = 0.5  # a grasp holds this long in a row (GT >= 1.27 s)
    gap_s: float = 0.1  # ... not counting gaps this short
    still_mm: float = 20.0  # object motion allowed while unheld (GT 0)
    still_deg: float = 10.0
    lift_m: float = 0.10  # lift: rise above the start (GT >= 15 cm)
    raise_m: float = 0.20  # inspect: rise (GT >= 37 cm)
    mouth_m: float = 0.15  # drink: head joint to the object's surface (GT <= 12 cm)
    face_m: float = 0.45  # inspect: head joint to the object's surface (GT <= 38 cm)
    turn_deg: float = 15.0  # inspect: rotation range while near the face (GT >= 21 deg)
    pour_deg: float = 35.0  # pour: tilt of the object's up axis (GT >= 53 deg)
    reach_frac: float = 0.80  # offhand: wrist-shoulder distance / arm length (GT >= 0.86)
    ahead_m: float = 0.30  # offhand: object ahead of the shoulders along the hips' forward (GT >= 38 cm)
    below_shoulder_m: float = 0.35  # offhand: ... and at most this far below them (GT <= 29 cm)


@dataclass
class CheckResult:
    intent: Intent
    rules: dict[str, bool] = field(default_factory=dict)  # rule -> passed, for the rules that apply
    values: dict[str, float] = field(default_factory=dict)  # what the rules measured
    reasons: list[str] = field(default_factory=list)  # one line per failed rule

    @property
    def ok(self) -> bool:
        return bool(self.rules) and all(self.rules.values())

    @property
    def reason(self) -> str:
        return "; ".join(self.reasons)

    def row(self) -> dict[str, float]:
        """0/1 per rule (``intent_<rule>``) and overall (``intent_ok``): means are rates."""
        return {"intent_ok": float(self.ok), **{f"intent_{k}": float(v) for k, v in self.rules.items()}}

    def rule(self, name: str, ok: bool, why: str) -> None:
        self.rules[name] = bool(ok)
        if not ok:
            self.reasons.append(f"{name}: {why}")


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    d = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def _to_object(track: MotionTrack, points: np.ndarray, frames=slice(None)) -> np.ndarray:
    """World points (T, K, 3) of ``frames`` -> signed distances (T, K) to the object."""
    local = np.einsum("tji,tkj->tki", track.object_rot[frames], points - track.object_transl[frames, None])
    return track.object_sdf(local)


def hold_masks(track: MotionTrack, cfg: CheckConfig = CheckConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(held, gripped), each (T, 2) bool: flag on and hand near the surface; and the runs of
    ``held`` at least ``min_hold_s`` long once gaps up to ``gap_s`` are filled (a generated
    flag that flickers off for a frame has not let go)."""
    dist = _to_object(track, track.joints[:, list(_HAND_JOINTS)])
    held = np.asarray(track.contact, bool) & (dist.reshape(len(dist), 2, -1).min(axis=-1) <= cfg.near_m)
    gripped = held.copy()
    min_len, max_gap = (max(1, int(round(s * track.fps))) for s in (cfg.min_hold_s, cfg.gap_s))
    for k in range(2):
        for a, b in _runs(~held[:, k]):
            gripped[a:b, k] |= 0 < a and b < len(held) and b - a <= max_gap
        for a, b in _runs(gripped[:, k]):
            gripped[a:b, k] = b - a >= min_len
    return held, gripped


def _grasp_rule(res: CheckResult, held: np.ndarray, gripped: np.ndarray, fps: float) -> None:
    v = res.values
    for k, s in enumerate(SIDES):
        v[f"hold_{s}_s"] = max((b - a for a, b in _runs(held[:, k])), default=0) / fps
    grasping = [s for k, s in enumerate(SIDES) if gripped[:, k].any()]
    named = res.intent.sides
    if not named:
        res.rule("grasp", bool(grasping), "no hand grasps")
        return
    missing = [s for s in named if s not in grasping]
    if missing:
        res.rule("grasp", False, f"the {' and '.join(missing)} hand does not grasp "
                                 f"(grasping: {', '.join(grasping) or 'none'})")
    elif len(named) == 1:  # the named hand does the holding
        other = SIDES[1 - SIDES.index(named[0])]
        res.rule("grasp", v[f"hold_{other}_s"] <= v[f"hold_{named[0]}_s"],
                 f"the {other} hand holds longer than the {named[0]}")
    else:
        res.rule("grasp", True, "")


def _pass_rule(res: CheckResult, gripped: np.ndarray) -> None:
    if not gripped.any(axis=0).all():
        res.rule("pass", False, "not both hands grasp it")
        return
    starts = [int(np.argmax(gripped[:, k])) for k in range(2)]
    ends = [len(gripped) - int(np.argmax(gripped[::-1, k])) for k in range(2)]
    first = SIDES[int(np.argmin(starts))] if starts[0] != starts[1] else None
    last = SIDES[int(np.argmax(ends))] if ends[0] != ends[1] else None
    hands = res.intent.hands
    giver, taker = hands.split(">") if hands and ">" in hands else (first, last)
    res.rule("pass", giver is not None and giver != taker and (first, last) == (giver, taker),
             f"asked {giver or '?'} to {taker or '?'}, the first to grasp is {first or 'a tie'}, "
             f"the last to hold {last or 'a tie'}")


def _offhand_reach(track: MotionTrack, gripped: np.ndarray, cfg: CheckConfig) -> float:
    """Largest holding arm extension (share of its length) over grasped frames where the
    object is out in front of the shoulders at about chest height or above."""
    j = track.joints
    arm_len = np.array([np.linalg.norm(j[0, e] - j[0, s]) + np.linalg.norm(j[0, w] - j[0, e]) for s, e, w in _ARMS])
    ext = np.stack([np.linalg.norm(j[:, w] - j[:, s], axis=-1) for s, _, w in _ARMS], axis=1) / arm_len
    facing = np.cross(j[:, _HIPS[0]] - j[:, _HIPS[1]], [0.0, 0.0, 1.0])[:, :2]  # the body's forward
    facing /= np.maximum(np.linalg.norm(facing, axis=-1, keepdims=True), 1e-9)
    rel = track.object_transl - 0.5 * (j[:, _ARMS[0][0]] + j[:, _ARMS[1][0]])
    out = ((rel[:, :2] * facing).sum(-1) >= cfg.ahead_m) & (rel[:, 2] >= -cfg.below_shoulder_m)
    return float(np.where(gripped & out[:, None], ext, 0.0).max())


def _intent_rule(res: CheckResult, track: MotionTrack, gripped: np.ndarray, cfg: CheckConfig) -> None:
    """The rule of the prompt's SynthGrasp intent."""
    name, v = res.intent.intent, res.values
    if name == "pass":
        _pass_rule(res, gripped)
        return
    f = np.nonzero(gripped.any(axis=1))[0]
    if not len(f):
        res.rule(name, False, "the object is never grasped")
        return
    z = track.object_transl[:, 2]
    v["rise_m"] = float((z[f] - z[0]).max())
    head_dist = _to_object(track, track.joints[f, sk.HEAD][:, None], f)[:, 0]
    v["head_m"] = float(head_dist.min())
    if name == "lift":
        res.rule(name, v["rise_m"] >= cfg.lift_m, f"rises {v['rise_m'] * 100:.0f} cm < {cfg.lift_m * 100:.0f}")
    elif name == "drink":
        res.rule(name, v["head_m"] <= cfg.mouth_m,
                 f"comes no nearer than {v['head_m'] * 100:.0f} cm to the head > {cfg.mouth_m * 100:.0f}")
    elif name == "pour":
        up_z = track.object_rot[f, 2, 2]  # world z of the object's up axis
        v["tilt_deg"] = float(np.degrees(np.arccos(np.clip(up_z, -1.0, 1.0))).max())
        res.rule(name, v["tilt_deg"] >= cfg.pour_deg, f"tilts {v['tilt_deg']:.0f} deg < {cfg.pour_deg:.0f}")
    elif name == "inspect":
        rot = track.object_rot[f[head_dist <= cfg.face_m]]
        v["turn_deg"] = float(rotation_angle_deg(rot[:, None], rot[None]).max()) if len(rot) else 0.0
        res.rule(name, v["rise_m"] >= cfg.raise_m and v["head_m"] <= cfg.face_m and v["turn_deg"] >= cfg.turn_deg,
                 f"rises {v['rise_m'] * 100:.0f} cm, comes {v['head_m'] * 100:.0f} cm from the head, turns "
                 f"{v['turn_deg']:.0f} deg there (need {cfg.raise_m * 100:.0f}, {cfg.face_m * 100:.0f}, "
                 f"{cfg.turn_deg:.0f})")
    elif name == "offhand":
        v["reach_frac"] = _offhand_reach(track, gripped, cfg)
        res.rule(name, v["reach_frac"] >= cfg.reach_frac,
                 f"never held out: arm at most {v['reach_frac']:.0%} of its length while the object is "
                 f">= {cfg.ahead_m * 100:.0f} cm ahead of the shoulders and <= {cfg.below_shoulder_m * 100:.0f} "
                 f"cm below (need {cfg.reach_frac:.0%})")


def check_motion(track: MotionTrack, intent: Intent, cfg: CheckConfig = CheckConfig()) -> CheckResult:
    """Check ``track`` against ``intent`` (the module doc lists the rules). An intent that is
    not SynthGrasp's (or UNKNOWN) gets the grasp and unheld-object rules only."""
    res = CheckResult(intent)
    held, gripped = hold_masks(track, cfg)
    _grasp_rule(res, held, gripped, track.fps)
    mm, deg = unheld_object_motion(track.object_rot, track.object_transl, held.any(axis=1))
    res.values.update(unheld_mm=mm, unheld_deg=deg)
    res.rule("unheld_still", mm <= cfg.still_mm and deg <= cfg.still_deg,
             f"the object moves {mm:.0f} mm / {deg:.0f} deg while no hand holds it")
    if intent.intent in SYNTH_INTENTS:
        _intent_rule(res, track, gripped, cfg)
    return res


def grasp_offsets(track: MotionTrack) -> np.ndarray:
    """(n, 3) world offsets, one per hand whose contact flag ever comes on: that hand's wrist in
    the first flagged frame minus the object's origin in the first frame (where the motion put
    the object at rest). Where a motion closes its hand relative to its own object: on a
    model's raw frames a systematic offset is what the contact stage's reach correction has
    to make up (docs/training.md, "The object's rest height"). Needs no object shape."""
    flags = np.asarray(track.contact, bool)
    return np.array([track.joints[np.argmax(flags[:, k]), _ARMS[k][2]] - track.object_transl[0]
                     for k in (0, 1) if flags[:, k].any()]).reshape(-1, 3)


# ---- from features ------------------------------------------------------------------------


def object_sdf_for(meta: dict) -> Callable[[np.ndarray], np.ndarray]:
    """The object's SDF from its mesh (``meta['object_mesh']``), else its catalogue shape."""
    from .objects.sdf import load_object_sdf

    mesh = meta.get("object_mesh")
    if mesh and Path(mesh).is_file():
        return load_object_sdf(mesh)
    if meta.get("object") in CATALOGUE:
        return CATALOGUE[meta["object"]].shape.sdf
    raise FileNotFoundError(f"no mesh or catalogue shape for object {meta.get('object')!r} ({mesh})")


def _shape_unknown(points: np.ndarray) -> np.ndarray:
    raise ValueError("this track was made without the object's shape (track_from_features(..., object_sdf))")


def track_from_features(x: np.ndarray, rest_joints: np.ndarray, fps: float,
                        object_sdf: Callable[[np.ndarray], np.ndarray] = _shape_unknown) -> MotionTrack:
    """A track from de-normalized (T, 335) features, through the inversion generated
    motions take (FK of the rotations, the object pose and contact columns). Without
    ``object_sdf`` only measures that need no shape (``grasp_offsets``) work on it."""
    rest = torch.as_tensor(np.asarray(rest_joints), dtype=torch.float64)
    joints = features_to_joints(torch.as_tensor(np.asarray(x), dtype=torch.float64), rest).numpy()
    p = features_to_params(x, rest)
    return MotionTrack(joints, p["object_rotmat"], p["object_transl"], p["contact"], float(fps), object_sdf)


def track_from_engine(frames: dict, object_sdf: Callable[[np.ndarray], np.ndarray]) -> MotionTrack:
    """A track from the engine's own frames: ``comgrasp generate --fk --out motion.npz`` in
    the native coordinate system (z up, metres; quaternions x, y, z, w)."""
    from .rotations import quaternion_to_matrix

    if "joint_positions" not in frames:
        raise ValueError("the engine's frames have no joint_positions: generate them with --fk")
    q = torch.as_tensor(np.asarray(frames["object_rotation"], np.float64))
    rot = quaternion_to_matrix(q[..., [3, 0, 1, 2]]).numpy()
    return MotionTrack(np.asarray(frames["joint_positions"], np.float64), rot,
                       np.asarray(frames["object_translation"], np.float64),
                       np.asarray(frames["contact"]).astype(bool), float(frames["fps"]), object_sdf)


def intent_of(meta: dict) -> Intent:
    """What a prepared sequence's prompts ask for, from its meta rather than its wording (for
    paraphrases the parser does not read): its intent, object and hand(s) (a pass: giver>taker)."""
    hands = meta.get("hands")
    if meta.get("intent") == "pass" and meta.get("first") and meta.get("last") and meta["first"] != meta["last"]:
        hands = f"{meta['first']}>{meta['last']}"
    return Intent(meta.get("intent"), hands, meta.get("object"))


def check_features(x: np.ndarray, text: str, meta: dict, rest_joints: np.ndarray, fps: float,
                   cfg: CheckConfig = CheckConfig(), intent: Intent | None = None) -> CheckResult:
    """Check one (T, 335) feature sequence against its prompt (or ``intent``, when given)."""
    return check_motion(track_from_features(x, rest_joints, fps, object_sdf_for(meta)),
                        parse_prompt(text) if intent is None else intent, cfg)


def intent_rates(results: list[CheckResult]) -> dict[str, float]:
    """``intent_ok`` (share passing every rule) and ``intent_<rule>`` (share passing that
    rule among the results it applies to)."""
    rows = [r.row() for r in results]
    order = ["intent_ok"] + [f"intent_{k}" for k in ("grasp", "unheld_still", *SYNTH_INTENTS)]
    keys = sorted({k for row in rows for k in row}, key=lambda k: (order.index(k) if k in order else len(order), k))
    return {k: float(np.mean([row[k] for row in rows if k in row])) for k in keys}


def check_feature_set(fs, limit: int | None = None, cfg: CheckConfig = CheckConfig()) -> list[CheckResult]:
    """Each sequence of a :class:`~comgrasp_train.dataset.FeatureSet` against its first text."""
    return [check_features(fs.features[i], fs.texts[i][0], fs.meta[i], fs.rest_joints[i], fs.fps, cfg)
            for i in range(len(fs.features[:limit]))]
