"""SynthGrasp subjects: ten open-skeleton bodies with GRAB's ids and genders.

GRAB has ten subjects (s1, s2, s8, s9, s10 male; s3..s7 female, reference §2.3); SynthGrasp
uses the same ids so subject splits carry over. Each subject is the open skeleton scaled by
its own :class:`~comgrasp_train.skeleton.Proportions` (our own numbers, not GRAB's
shapes). The files a consumer needs are written in GRAB's layout:
``tools/subject_meshes/<gender>/s<k>.ply`` (a capsule mesh of the rest pose, so ``vtemp``
points at a real mesh), ``s<k>_skeleton.npy`` (the rest joints the open body model reads)
and ``s<k>_{l,r}hand.ply`` (the hand capsules, GRAB's per-subject hand templates).

In the world the subject stands upright facing +y (z up), the pelvis fixed, the legs in
the rest pose, the lowest foot proxy point on the floor z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import numpy as np
import trimesh

from .. import skeleton as sk
from ..body_model import BodyModelConfig
from ..surface import FOOT_CODES, LEFT_HAND_CODES, RIGHT_HAND_CODES, SurfaceProxy, build_proxy

# Canonical SMPL-X frame (y up, +z forward, left +x) -> world (z up, facing +y): the columns
# are the world images of canonical x, y, z. Canonical left (+x) lands on world -x.
ROOT_ROT = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class SubjectSpec:
    sbj_id: str
    gender: str
    proportions: sk.Proportions


def _p(height, arm, leg, shoulder, hip, hand, torso) -> sk.Proportions:
    return sk.Proportions(height=height, arm=arm, leg=leg, shoulder_width=shoulder, hip_width=hip,
                          hand=hand, torso=torso)


# Every proportion of a validation or test subject (s8; s9, s10 in the `synthgrasp` split)
# lies inside the training subjects' range (s1-s7): a held-out subject is a new person of
# the same population, not a taller one. When s8 and s10 were the two tallest, the VQ had to
# extrapolate the absolute pelvis height it encodes: held-out reconstruction was ~35 mm worse
# on s10 than on s9 (MPJPE 104 against 69 mm, its root height 44 against 21 mm off;
# docs/training.md, "Held-out subjects").
SUBJECTS: tuple[SubjectSpec, ...] = (
    SubjectSpec("s1", "male", _p(1.08, 1.04, 1.05, 1.07, 1.00, 1.06, 1.02)),
    SubjectSpec("s2", "male", _p(1.03, 1.01, 1.02, 1.04, 0.98, 1.02, 1.01)),
    SubjectSpec("s3", "female", _p(0.94, 0.97, 0.99, 0.93, 1.04, 0.93, 0.97)),
    SubjectSpec("s4", "female", _p(0.97, 1.01, 1.02, 0.95, 1.06, 0.95, 0.96)),
    SubjectSpec("s5", "female", _p(0.91, 0.96, 0.95, 0.92, 1.03, 0.92, 0.98)),
    SubjectSpec("s6", "female", _p(0.95, 0.99, 1.00, 0.94, 1.05, 0.94, 0.95)),
    SubjectSpec("s7", "female", _p(0.92, 1.02, 0.98, 0.91, 1.02, 0.91, 0.97)),
    SubjectSpec("s8", "male", _p(0.99, 0.98, 0.97, 1.02, 1.00, 0.99, 1.02)),
    SubjectSpec("s9", "male", _p(1.01, 0.97, 1.00, 1.03, 0.98, 1.00, 1.02)),
    SubjectSpec("s10", "male", _p(1.06, 1.03, 1.04, 1.06, 0.99, 1.05, 1.00)),
)
SUBJECT = {s.sbj_id: s for s in SUBJECTS}


def vtemp_path(spec: SubjectSpec) -> str:
    """The subject mesh path relative to the dataset root, as GRAB writes ``body/vtemp``."""
    return f"tools/subject_meshes/{spec.gender}/{spec.sbj_id}.ply"


@dataclass(frozen=True)
class SubjectModel:
    """A subject's rest skeleton, surface proxy and standing placement (pelvis at x = y = 0)."""

    spec: SubjectSpec

    @cached_property
    def rest(self) -> np.ndarray:
        return sk.scaled_rest_joints(self.spec.proportions)

    @cached_property
    def proxy(self) -> SurfaceProxy:
        # The same sampling as the open body model's, so contact/body indexes its points.
        cfg = BodyModelConfig()
        return build_proxy(self.rest, cfg.hand_spacing, cfg.body_spacing)

    @cached_property
    def body_capsules(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ends (K, 3) x2, radii and carrying joints of the proxy capsules outside the hands."""
        hands = set(LEFT_HAND_CODES) | set(RIGHT_HAND_CODES)
        caps = [c for c in self.proxy.capsules if c.code not in hands]
        return (np.stack([c.a for c in caps]), np.stack([c.b for c in caps]), np.array([c.radius for c in caps]),
                np.array([c.joint for c in caps]))

    @cached_property
    def pelvis_height(self) -> float:
        """World z of the pelvis that puts the lowest foot proxy point on the floor."""
        feet = self.proxy.rest_points[self.proxy.mask(FOOT_CODES)] - self.rest[0]
        return float(-(feet @ ROOT_ROT.T)[:, 2].min())


@cache
def subject_model(sbj_id: str) -> SubjectModel:
    return SubjectModel(SUBJECT[sbj_id])


def _capsule_mesh(proxy: SurfaceProxy, codes=None) -> trimesh.Trimesh:
    parts = []
    for c in proxy.capsules:
        if codes is not None and c.code not in codes:
            continue
        axis = c.b - c.a
        length = float(np.linalg.norm(axis))
        m = trimesh.creation.capsule(height=length, radius=c.radius, count=[8, 8])
        tf = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], axis / length)
        tf[:3, 3] = (c.a + c.b) / 2.0
        m.apply_transform(tf)
        parts.append(m)
    return trimesh.util.concatenate(parts)


def write_subject_files(root: Path, specs: tuple[SubjectSpec, ...] = SUBJECTS) -> dict[str, str]:
    """Write every subject's rest mesh, skeleton and hand meshes under ``root/tools``;
    returns sbj_id -> vtemp (relative path)."""
    out = {}
    for spec in specs:
        model = subject_model(spec.sbj_id)
        rel = vtemp_path(spec)
        path = Path(root) / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        stem = str(path)[: -len(".ply")]
        np.save(f"{stem}_skeleton.npy", model.rest)
        _capsule_mesh(model.proxy).export(path)
        _capsule_mesh(model.proxy, set(LEFT_HAND_CODES)).export(f"{stem}_lhand.ply")
        _capsule_mesh(model.proxy, set(RIGHT_HAND_CODES)).export(f"{stem}_rhand.ply")
        out[spec.sbj_id] = rel
    return out
