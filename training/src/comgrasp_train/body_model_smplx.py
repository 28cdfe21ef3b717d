"""The ``smplx`` body-model backend: the user's SMPL-X files through the `smplx` package.

Licence: SMPL-X model files and the `smplx` package are for non-commercial use only. This
module contains no SMPL-X code or data: it imports the `smplx` package (``pip install smplx``,
installed by the user) and reads the model files the user downloaded from
https://smpl-x.is.tue.mpg.de. Point ``BodyModelConfig.smplx_model_dir`` at the folder that
holds ``smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz`` (or at the ``smplx`` folder itself).

How a GRAB subject is built (GRAB and GOAL do the same, see the reference spec §1.4/§4.7):

* The personalised template is GRAB's ``body/vtemp`` mesh (10475 vertices). It already holds
  the subject's shape, so betas and expression stay zero.
* Rest joints are ``J_regressor @ v_template`` (the 55 LBS joints), in float64.
* Joints and global rotations come from :func:`skeleton.forward_kinematics` with those rest
  joints. That FK uses SMPL-X's LBS chain (root ``[R_0 | J_0]``, ``transl`` added last), so
  with zero betas it equals ``smplx``'s first 55 output joints exactly.
* Vertices come from ``smplx.SMPLXLayer`` driven by rotation matrices. The layer never adds
  the hand mean pose and uses no PCA, which is right for GRAB's ``fullpose`` hands: they are
  absolute axis-angle with the hand mean already included (spec §4.6/§4.7).
* Per-vertex part codes are ``argmax_j(lbs_weights[v, j]) + 1`` (GRAB's contact code is
  "SMPL-X joint index + 1"). That this reproduces GRAB/GOAL's ``vertex_label_contact.npy``
  is our inference (spec §2.5), not something a primary source states.

One layer is built per (gender, device, dtype) and shared by that gender's subjects; each
subject keeps its own template, which is put into the layer's ``v_template`` buffer for the
duration of a call (a full SMPL-X layer holds about 60 MB of pose correctives, so one per
subject would add up). ``forward`` is therefore not meant to be called from several threads
at once on the same instance.
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import skeleton as sk
from .body_model import BodyModel, BodyModelConfig, BodyOutput, Subject

NUM_VERTICES = 10475
GENDERS = ("male", "female", "neutral")
# SMPLXLayer's full-pose order (global, body 1-21, jaw, leye, reye, left hand, right hand)
# is the SMPL-X joint order 0..54, so each argument is a contiguous slice of rotmats.
_POSE_SLICES = {
    "global_orient": slice(0, 1),
    "body_pose": slice(1, 22),
    "jaw_pose": slice(22, 23),
    "leye_pose": slice(23, 24),
    "reye_pose": slice(24, 25),
    "left_hand_pose": slice(25, 40),
    "right_hand_pose": slice(40, 55),
}

_INSTALL_HINT = (
    "body_model.backend='smplx' needs the `smplx` Python package, which is not installed. "
    "Install it with `pip install smplx` (note: smplx and the SMPL-X model files are for "
    "non-commercial use only), or use body_model.backend='open'."
)


def _import_smplx():
    try:
        import smplx  # optional dependency, imported on use
    except ImportError as e:
        raise ImportError(_INSTALL_HINT) from e
    return smplx


def model_file_candidates(model_dir: str | Path, gender: str) -> list[Path]:
    """Where the SMPL-X file of ``gender`` is looked for, in order."""
    name = f"SMPLX_{gender.upper()}.npz"
    d = Path(model_dir).expanduser()
    return [d / "smplx" / name, d / name]


def _norm_gender(gender) -> str:
    if isinstance(gender, bytes):
        gender = gender.decode()
    g = str(gender).strip().lower()
    if g not in GENDERS:
        raise ValueError(f"smplx body model: gender must be one of {GENDERS}, got {gender!r}")
    return g


@dataclass(frozen=True)
class _ModelData:
    path: Path
    v_template: np.ndarray  # (V, 3) float64, the model's own template
    j_regressor: np.ndarray  # (55, V) float64
    vertex_code: np.ndarray  # (V,) int64 GRAB part code = argmax LBS weight + 1


def _dense(a) -> np.ndarray:
    if hasattr(a, "toarray"):  # a scipy.sparse matrix stored as an object
        a = a.toarray()
    return np.asarray(a, dtype=np.float64)


def _load_model_data(path: Path) -> _ModelData:
    try:
        with np.load(path, allow_pickle=True) as d:  # the smplx package loads it the same way
            missing = [k for k in ("v_template", "J_regressor", "weights", "kintree_table") if k not in d.files]
            if missing:
                raise ValueError(f"missing key(s) {missing}; is this an SMPL-X model file?")
            v_template = _dense(d["v_template"])
            j_reg = d["J_regressor"]
            j_reg = _dense(j_reg.item() if j_reg.dtype == object and j_reg.ndim == 0 else j_reg)
            weights = _dense(d["weights"])
            parents = np.asarray(d["kintree_table"])[0].astype(np.int64)
    except (OSError, ValueError, KeyError, EOFError) as e:
        raise ValueError(f"smplx body model: cannot read SMPL-X model file {path}: {e}") from e
    j = sk.NUM_JOINTS
    if v_template.shape != (NUM_VERTICES, 3) or j_reg.shape[1:] != (NUM_VERTICES,) or j_reg.shape[0] < j \
            or weights.shape[0] != NUM_VERTICES or weights.shape[1] < j:
        raise ValueError(
            f"smplx body model: {path} is not an SMPL-X model: v_template {v_template.shape}, "
            f"J_regressor {j_reg.shape}, weights {weights.shape} (expected ({NUM_VERTICES}, 3), "
            f"({j}, {NUM_VERTICES}), ({NUM_VERTICES}, {j}))"
        )
    if parents.shape[0] < j or not np.array_equal(parents[1:j], np.asarray(sk.PARENTS[1:])):
        raise ValueError(f"smplx body model: {path}: kintree_table parents differ from SMPL-X's 55-joint tree")
    return _ModelData(
        path=path,
        v_template=v_template,
        j_regressor=j_reg[:j],
        vertex_code=np.argmax(weights[:, :j], axis=1).astype(np.int64) + 1,
    )


def read_vtemp(path: str | Path) -> np.ndarray:
    """Vertices (10475, 3) float64 of a GRAB subject template mesh (``body/vtemp``)."""
    import trimesh

    try:
        m = trimesh.load(str(path), process=False, force="mesh")
        verts = np.asarray(m.vertices, dtype=np.float64)
    except Exception as e:  # trimesh raises many types on a bad file
        raise ValueError(f"smplx body model: cannot read subject template {path}: {e}") from e
    if verts.shape != (NUM_VERTICES, 3):
        raise ValueError(
            f"smplx body model: subject template {path} has {verts.shape[0]} vertices; an SMPL-X "
            f"template (GRAB body/vtemp) has {NUM_VERTICES}"
        )
    if not np.isfinite(verts).all():
        raise ValueError(f"smplx body model: subject template {path} has non-finite vertices")
    return verts


class SmplxBody(BodyModel):
    backend = "smplx"

    def __init__(self, cfg: BodyModelConfig, chunk_size: int = 256):
        self.cfg = cfg
        self.chunk_size = int(chunk_size)  # frames per SMPLXLayer call when computing vertices
        if not cfg.smplx_model_dir:
            raise ValueError(
                "body_model.backend='smplx' needs body_model.smplx_model_dir "
                "(BodyModelConfig.smplx_model_dir): the folder holding "
                "smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz from https://smpl-x.is.tue.mpg.de"
            )
        self.model_dir = Path(cfg.smplx_model_dir).expanduser()
        if not self.model_dir.is_dir():
            raise FileNotFoundError(
                f"body_model.smplx_model_dir={str(cfg.smplx_model_dir)!r} is not a folder "
                "(expected one holding smplx/SMPLX_{MALE,FEMALE,NEUTRAL}.npz)"
            )
        looked = [p for g in GENDERS for p in model_file_candidates(self.model_dir, g)]
        if not any(p.is_file() for p in looked):
            raise FileNotFoundError(
                f"no SMPL-X model file under body_model.smplx_model_dir={str(cfg.smplx_model_dir)!r}; "
                "looked for: " + ", ".join(str(p) for p in looked)
            )
        self._smplx = _import_smplx()
        self._data: dict[str, _ModelData] = {}
        self._layers: dict[tuple, torch.nn.Module] = {}
        self._cache: dict[str, Subject] = {}

    # ----------------------------------------------------------------- model files
    def model_file(self, gender: str) -> Path:
        g = _norm_gender(gender)
        cands = model_file_candidates(self.model_dir, g)
        for p in cands:
            if p.is_file():
                return p
        raise FileNotFoundError(
            f"smplx body model: no {g} SMPL-X model; looked for: " + ", ".join(str(p) for p in cands)
        )

    def _model_data(self, gender: str) -> _ModelData:
        if gender not in self._data:
            self._data[gender] = _load_model_data(self.model_file(gender))
        return self._data[gender]

    def layer(self, gender: str, device=None, dtype: torch.dtype = torch.float32) -> torch.nn.Module:
        """The shared ``smplx.SMPLXLayer`` of a gender on a device/dtype (built once)."""
        g = _norm_gender(gender)
        device = torch.device(device) if device is not None else torch.device("cpu")
        key = (g, str(device), dtype)
        if key not in self._layers:
            base_key = (g, "cpu", torch.float32)
            if base_key not in self._layers:
                base = self._smplx.SMPLXLayer(
                    model_path=str(self.model_file(g)), gender=g, num_betas=10,
                    num_expression_coeffs=10, use_pca=False, flat_hand_mean=True, dtype=torch.float32,
                )
                base.eval()
                self._layers[base_key] = base
            if key != base_key:
                self._layers[key] = copy.deepcopy(self._layers[base_key]).to(device=device, dtype=dtype)
        return self._layers[key]

    # ----------------------------------------------------------------- subjects
    def subject(self, gender: str, vtemp: str | Path | None = None) -> Subject:
        g = _norm_gender(gender)
        key = f"{g}:{vtemp}"
        if key in self._cache:
            return self._cache[key]
        data = self._model_data(g)
        if vtemp is not None and Path(vtemp).is_file():
            v = read_vtemp(vtemp)
            source = str(vtemp)
        else:
            warnings.warn(
                f"smplx body model: subject template {vtemp!r} not found; using the SMPL-X {g} "
                "model's own template, so joints and vertices will not match this subject's shape",
                stacklevel=2,
            )
            v = data.v_template
            source = None
        rest = data.j_regressor @ v  # (55, 3) float64
        subj = Subject(
            key=key, gender=g, rest_joints=torch.from_numpy(np.ascontiguousarray(rest)),
            vertex_code=data.vertex_code,
            extra={"v_template": torch.from_numpy(np.ascontiguousarray(v)), "vtemp": source,
                   "model_file": str(data.path)},
        )
        self._cache[key] = subj
        return subj

    # ----------------------------------------------------------------- forward
    def forward(self, subject: Subject, rotmats: torch.Tensor, transl: torch.Tensor | None,
                vertices: bool = False) -> BodyOutput:
        """rotmats (..., 55, 3, 3) local rotations, transl (..., 3) -> joints (..., 55, 3),
        global rotations (..., 55, 3, 3) and, when asked, vertices (..., 10475, 3)."""
        if rotmats.shape[-3:] != (sk.NUM_JOINTS, 3, 3):
            raise ValueError(f"rotmats must be (..., 55, 3, 3), got {tuple(rotmats.shape)}")
        rest = subject.rest_joints.to(device=rotmats.device, dtype=rotmats.dtype)
        if transl is not None:
            transl = transl.to(device=rotmats.device, dtype=rotmats.dtype)
        g_rot, joints = sk.forward_kinematics(rotmats, rest, transl)
        verts = self._vertices(subject, rotmats, transl) if vertices else None
        return BodyOutput(joints, g_rot, verts)

    def _vertices(self, subject: Subject, rotmats: torch.Tensor, transl: torch.Tensor | None) -> torch.Tensor:
        lead = rotmats.shape[:-3]
        rot = rotmats.reshape(-1, sk.NUM_JOINTS, 3, 3)
        n = rot.shape[0]
        dev, dt = rot.device, rot.dtype
        if transl is None:
            tr = torch.zeros(n, 3, device=dev, dtype=dt)
        else:
            try:
                tr = transl.expand(*lead, 3).reshape(n, 3)
            except RuntimeError as e:
                raise ValueError(f"transl {tuple(transl.shape)} does not match rotmats {tuple(rotmats.shape)}") from e
        layer = self.layer(subject.gender, dev, dt)
        # The subject's template replaces the layer's for this call (see the module docstring).
        layer.v_template = subject.extra["v_template"].to(device=dev, dtype=dt)
        out = []
        for s in range(0, n, max(1, self.chunk_size)):
            r = rot[s:s + self.chunk_size]
            b = r.shape[0]
            res = layer(
                betas=torch.zeros(b, layer.num_betas, device=dev, dtype=dt),
                expression=torch.zeros(b, layer.num_expression_coeffs, device=dev, dtype=dt),
                transl=tr[s:s + b],
                return_verts=True,
                **{name: r[:, sl] for name, sl in _POSE_SLICES.items()},
            )
            out.append(res.vertices)
        verts = torch.cat(out, 0) if out else torch.zeros(0, NUM_VERTICES, 3, device=dev, dtype=dt)
        return verts.reshape(*lead, NUM_VERTICES, 3)
