"""How a hand takes hold of an upright object: grasp style, direction and height.

'side': the palm on the side facing the hand (a handle if there is one), thumb up and
rolled toward the arm's line; 'top': the palm on top, fingers forward (on a ring, on the
rim). Faces of boxes and pyramids are aligned with the palm. The hand stays above a floor
(the table, or the object's bottom when it will be put down by this hand), then
``grasp.make_grasp`` closes it on the surface.
"""

from __future__ import annotations

import numpy as np

from ..objects.catalogue import ObjectSpec
from .grasp import Grasp, Obstacles, make_grasp
from .ik import axis_angle, unit
from .scene import UP, Scene

_BOXY = ("box", "pyramid")  # shapes with faces: side/top grasps are aligned to a face


def _boxy(obj: ObjectSpec) -> bool:
    return any(p.kind in _BOXY for p in obj.shape.parts)


def _snap_to_faces(direction: np.ndarray, obj_rot: np.ndarray) -> np.ndarray:
    """The object's horizontal face normal closest to a horizontal direction."""
    axes = np.concatenate([obj_rot[:, :2].T, -obj_rot[:, :2].T])
    return axes[np.argmax(axes @ direction)]


def turn(v: np.ndarray, angle: float) -> np.ndarray:
    """``v`` turned about the vertical."""
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
        for angle in (0.6 * roll + jitter, 0.3 * roll + jitter, jitter, 0.0):
            rot_w = axis_angle(normal, angle) @ upright
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
        if obj.shape.sdf(np.zeros(3)) > 0:  # a ring: the palm goes on the rim nearest the wrist
            ray = -(r_o.T @ direction) * np.array([1.0, 1.0, 0.0])
            radii = np.linspace(0.0, obj.half_extents[:2].max(), 64)
            target[:2] = radii[np.argmin(obj.shape.sdf(radii[:, None] * unit(ray)))] * unit(ray)[:2]
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


def first_grasp(scene: Scene, side: str, obj: ObjectSpec, verts: np.ndarray, pose, rng: np.random.Generator,
                base: dict[str, np.ndarray], spread: float, obstacles: Obstacles, floor: float, handle: bool,
                styles: list[str], tries: int = 4) -> Grasp | None:
    """``tries`` attempts per style, each turned randomly (by up to ``spread`` rad) about the
    vertical from the style's base direction; None if none holds."""
    for style in styles:
        for _ in range(tries):
            g = try_grasp(scene, side, obj, verts, pose, style, turn(base[style], rng.uniform(-spread, spread)),
                          rng, obstacles, floor, handle)
            if g is not None:
                return g
    return None
