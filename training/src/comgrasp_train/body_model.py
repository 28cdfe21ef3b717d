"""Body model interface with two backends, chosen by one config field.

* ``open`` (default): the open SMPL-X-topology skeleton (`skeleton.py`) with capsule surface
  proxies (`surface.py`) standing in for vertices. Needs no files. A subject's rest joints
  come from ``<vtemp without .ply>_skeleton.npy`` beside the subject mesh when present
  (SynthGrasp writes it); a real GRAB subject, which has none, uses the default skeleton.
* ``smplx``: the `smplx` package with the user's SMPL-X model files
  (``smplx_model_dir``), personalised by GRAB's ``vtemp`` mesh. Joints use the same FK chain
  with rest joints ``J_regressor @ v_template``; vertices come from the package.

Both return joints (B, 55, 3), global rotations (B, 55, 3, 3) and, on request, surface
points (B, V, 3) with per-point GRAB contact codes, so metrics are backend-agnostic.
"""

from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import skeleton as sk
from .surface import FOOT_CODES, LEFT_HAND_CODES, RIGHT_HAND_CODES, build_proxy, pose_points


@dataclass
class BodyModelConfig:
    backend: str = "open"  # "open" | "smplx"
    smplx_model_dir: str | None = None  # folder with smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz (or the files directly)
    hand_spacing: float = 0.004  # open proxy sampling (m)
    body_spacing: float = 0.02


@dataclass
class Subject:
    key: str
    gender: str
    rest_joints: torch.Tensor  # (55, 3) float64, rest pose in the SMPL-X canonical frame
    vertex_code: np.ndarray  # (V,) GRAB part code per surface point / vertex
    extra: dict = field(default_factory=dict)  # backend-specific (proxy tensors, smplx layer)

    def mask(self, codes) -> np.ndarray:
        return np.isin(self.vertex_code, np.asarray(list(codes)))

    @property
    def left_hand_mask(self) -> np.ndarray:
        return self.mask(LEFT_HAND_CODES)

    @property
    def right_hand_mask(self) -> np.ndarray:
        return self.mask(RIGHT_HAND_CODES)

    @property
    def foot_mask(self) -> np.ndarray:
        return self.mask(FOOT_CODES)


@dataclass
class BodyOutput:
    joints: torch.Tensor  # (B, 55, 3)
    global_rot: torch.Tensor  # (B, 55, 3, 3)
    vertices: torch.Tensor | None = None  # (B, V, 3)


class BodyModel:
    backend = "abstract"

    def subject(self, gender: str, vtemp: str | Path | None = None) -> Subject:
        raise NotImplementedError

    def forward(self, subject: Subject, rotmats: torch.Tensor, transl: torch.Tensor,
                vertices: bool = False) -> BodyOutput:
        raise NotImplementedError

    def __call__(self, *args, **kwargs) -> BodyOutput:
        return self.forward(*args, **kwargs)


class OpenSkeletonBody(BodyModel):
    backend = "open"

    def __init__(self, cfg: BodyModelConfig):
        self.cfg = cfg
        self._cache: dict[str, Subject] = {}
        self._warned = False

    def subject_from_rest(self, rest_joints: np.ndarray, gender: str = "neutral", key: str | None = None) -> Subject:
        rest = np.asarray(rest_joints, dtype=np.float64)
        proxy = build_proxy(rest, self.cfg.hand_spacing, self.cfg.body_spacing)
        return Subject(
            key=key or f"rest:{hashlib.sha1(rest.tobytes()).hexdigest()[:16]}", gender=gender,
            rest_joints=torch.from_numpy(rest), vertex_code=proxy.code,
            extra={"proxy_joint": torch.from_numpy(proxy.joint), "proxy_rest": torch.from_numpy(proxy.rest_points)},
        )

    def subject(self, gender: str, vtemp: str | Path | None = None) -> Subject:
        key = f"{gender}:{vtemp}"
        if key in self._cache:
            return self._cache[key]
        rest = None
        if vtemp is not None:
            skel = Path(str(vtemp)[: -len(".ply")] + "_skeleton.npy") if str(vtemp).endswith(".ply") else None
            if skel is not None and skel.is_file():
                rest = np.load(skel)
                if rest.shape != (sk.NUM_JOINTS, 3):
                    raise ValueError(f"{skel}: expected shape (55, 3), got {rest.shape}")
        if rest is None:
            if not self._warned:
                warnings.warn(
                    "open body model: no <subject>_skeleton.npy beside the subject mesh; using the "
                    "default skeleton (joint positions are approximate for real GRAB subjects; "
                    "set body_model.backend='smplx' with your SMPL-X files for exact ones)",
                    stacklevel=2,
                )
                self._warned = True
            rest = sk.DEFAULT_REST_JOINTS
        subj = self.subject_from_rest(rest, gender, key)
        self._cache[key] = subj
        return subj

    def forward(self, subject: Subject, rotmats: torch.Tensor, transl: torch.Tensor,
                vertices: bool = False) -> BodyOutput:
        rest = subject.rest_joints.to(rotmats.dtype)
        g_rot, joints = sk.forward_kinematics(rotmats, rest, transl)
        verts = None
        if vertices:
            verts = pose_points(subject.extra["proxy_joint"], subject.extra["proxy_rest"], rest, g_rot, joints)
        return BodyOutput(joints, g_rot, verts)


def make_body_model(cfg: BodyModelConfig | None = None) -> BodyModel:
    cfg = cfg or BodyModelConfig()
    if cfg.backend == "open":
        return OpenSkeletonBody(cfg)
    if cfg.backend == "smplx":
        from .body_model_smplx import SmplxBody  # imports the optional `smplx` package

        return SmplxBody(cfg)
    raise ValueError(f"body_model.backend must be 'open' or 'smplx', got {cfg.backend!r}")
