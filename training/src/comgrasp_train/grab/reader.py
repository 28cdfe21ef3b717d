"""Reader for GRAB sequence files (a user's download or SynthGrasp, same format).

Loads exactly GRAB's published layout (reference §1): 0-d pickled dicts, 120 fps, z-up
metres, axis-angle ``body/params/fullpose`` (55 joints, hands absolute, as GOAL/IMoS/
DiffGrasp use them) and object rotations in the ROW-vector convention, converted here to
the column convention (``R_world = rodrigues(global_orient)^T``). Mesh paths are resolved
against the dataset root. Per-hand contact comes from ``contact/object`` codes (left 21 and
26..40, right 22 and 41..55). The big per-vertex contact arrays are reduced on load.

A bad file raises :class:`GrabFormatError` naming the file and the problem;
:func:`load_dataset` skips such files with a message and counts them in its summary.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh

from .format import LEFT_HAND_CODES, RIGHT_HAND_CODES
from .splits import SplitConfig

log = logging.getLogger(__name__)


class GrabFormatError(ValueError):
    def __init__(self, path: Path | str, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = str(path)
        self.problem = problem


@dataclass
class GrabSequence:
    path: str
    sbj_id: str
    gender: str
    obj_name: str
    intent: str  # from the file's motion_intent
    framerate: float
    fullpose: np.ndarray  # (T, 55, 3) float32 axis-angle, SMPL-X joint order
    transl: np.ndarray  # (T, 3) SMPL-X transl
    object_rotmat: np.ndarray  # (T, 3, 3) column-vector world rotation
    object_transl: np.ndarray  # (T, 3)
    object_mesh: str  # absolute path
    vtemp: str  # absolute path of the subject template mesh (may not exist for SynthGrasp)
    contact: np.ndarray  # (T, 2) bool, [left, right] hand touches the object
    table_rotmat: np.ndarray | None = None
    table_transl: np.ndarray | None = None
    table_mesh: str | None = None
    object_contact_codes: np.ndarray | None = None  # (T, V_obj) int8, only when keep_vertex_contact
    extra: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.fullpose.shape[0])

    @property
    def name(self) -> str:
        p = Path(self.path)
        return f"{p.parent.name}/{p.stem}"


@dataclass
class LoadSummary:
    loaded: int = 0
    skipped: int = 0
    problems: list[str] = field(default_factory=list)

    def __str__(self) -> str:
        return f"loaded {self.loaded} sequences, skipped {self.skipped}"


def _rodrigues(aa: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(theta, 1e-12)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


@lru_cache(maxsize=256)
def mesh_vertex_count(path: str) -> int:
    """Vertices of a mesh file (cached); raises on an unreadable mesh."""
    m = trimesh.load(path, process=False, force="mesh")
    n = int(len(m.vertices))
    if n == 0:
        raise ValueError("mesh has no vertices")
    return n


def _get(d, key: str, path: Path, where: str):
    if not isinstance(d, dict) or key not in d:
        raise GrabFormatError(path, f"missing key '{where}{key}'")
    return d[key]


def _array(d, key: str, shape_tail: tuple[int, ...], T: int | None, path: Path, where: str) -> np.ndarray:
    a = np.asarray(_get(d, key, path, where))
    if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != shape_tail or (T is not None and a.shape[0] != T):
        want = ("T" if T is None else str(T),) + tuple(str(s) for s in shape_tail)
        raise GrabFormatError(path, f"'{where}{key}' has shape {a.shape}, expected ({', '.join(want)})")
    if not np.issubdtype(a.dtype, np.number):
        raise GrabFormatError(path, f"'{where}{key}' is not numeric (dtype {a.dtype})")
    if not np.all(np.isfinite(a)):
        raise GrabFormatError(path, f"'{where}{key}' contains NaN or Inf")
    return a


def _item(npz, key: str, path: Path):
    if key not in npz.files:
        raise GrabFormatError(path, f"missing key '{key}'")
    a = npz[key]
    return a.item() if a.ndim == 0 else a


def load_sequence(path: str | Path, root: str | Path, keep_vertex_contact: bool = False) -> GrabSequence:
    """Load one GRAB file. ``root`` is the dataset root (holds ``grab/`` and ``tools/``)."""
    path, root = Path(path), Path(root)
    try:
        npz = np.load(path, allow_pickle=True)
    except Exception as e:  # numpy falls back to unpickling non-zip files: any error is possible
        raise GrabFormatError(path, f"not a readable npz file ({type(e).__name__}: {e})") from e
    with npz:
        try:
            top = {k: _item(npz, k, path) for k in
                   ("gender", "sbj_id", "obj_name", "motion_intent", "framerate", "body", "object", "contact")}
            table = _item(npz, "table", path) if "table" in npz.files else None
            n_frames = _item(npz, "n_frames", path) if "n_frames" in npz.files else None
        except GrabFormatError:
            raise
        except Exception as e:  # a pickled entry that does not unpickle
            raise GrabFormatError(path, f"cannot read entry ({type(e).__name__}: {e})") from e

    for k in ("gender", "sbj_id", "obj_name", "motion_intent"):
        if not isinstance(top[k], str) or not top[k]:
            raise GrabFormatError(path, f"'{k}' must be a non-empty string, got {top[k]!r}")
    try:
        framerate = float(top["framerate"])
    except (TypeError, ValueError):
        raise GrabFormatError(path, f"'framerate' is not a number: {top['framerate']!r}") from None
    if not framerate > 0:
        raise GrabFormatError(path, f"'framerate' must be positive, got {framerate}")

    body = top["body"]
    params = _get(body, "params", path, "body/")
    fullpose = _array(params, "fullpose", (165,), None, path, "body/params/")
    T = fullpose.shape[0]
    if T < 2:
        raise GrabFormatError(path, f"sequence has {T} frames")
    if n_frames is not None and int(n_frames) != T:
        raise GrabFormatError(path, f"'n_frames' is {int(n_frames)} but body/params/fullpose has {T} frames")
    transl = _array(params, "transl", (3,), T, path, "body/params/")
    vtemp = _get(body, "vtemp", path, "body/")

    obj = top["object"]
    oparams = _get(obj, "params", path, "object/")
    o_t = _array(oparams, "transl", (3,), T, path, "object/params/")
    o_aa = _array(oparams, "global_orient", (3,), T, path, "object/params/")
    mesh_rel = _get(obj, "object_mesh", path, "object/")
    if not isinstance(mesh_rel, str):
        raise GrabFormatError(path, f"'object/object_mesh' must be a path string, got {type(mesh_rel).__name__}")
    mesh_path = root / mesh_rel
    try:
        n_vert = mesh_vertex_count(str(mesh_path))
    except Exception as e:
        raise GrabFormatError(path, f"object mesh {mesh_path} is unreadable ({e})") from e

    contact = top["contact"]
    c_obj = np.asarray(_get(contact, "object", path, "contact/"))
    if c_obj.shape != (T, n_vert) or not np.issubdtype(c_obj.dtype, np.number):
        raise GrabFormatError(path, f"'contact/object' has shape {c_obj.shape} ({c_obj.dtype}), expected "
                                    f"({T}, {n_vert}) numeric codes for mesh {mesh_rel}")
    codes = c_obj.astype(np.int16)
    left = np.isin(codes, list(LEFT_HAND_CODES)).any(axis=1)
    right = np.isin(codes, list(RIGHT_HAND_CODES)).any(axis=1)

    t_rot = t_tr = t_mesh = None
    if isinstance(table, dict) and "params" in table:
        t_tr = _array(table["params"], "transl", (3,), T, path, "table/params/").astype(np.float32)
        t_rot = np.swapaxes(_rodrigues(_array(table["params"], "global_orient", (3,), T, path,
                                              "table/params/").astype(np.float64)), -1, -2).astype(np.float32)
        if isinstance(table.get("table_mesh"), str):
            t_mesh = str(root / table["table_mesh"])

    return GrabSequence(
        path=str(path), sbj_id=top["sbj_id"], gender=top["gender"], obj_name=top["obj_name"],
        intent=top["motion_intent"], framerate=framerate,
        fullpose=fullpose.reshape(T, 55, 3).astype(np.float32), transl=transl.astype(np.float32),
        object_rotmat=np.swapaxes(_rodrigues(o_aa.astype(np.float64)), -1, -2).astype(np.float32),
        object_transl=o_t.astype(np.float32), object_mesh=str(mesh_path),
        vtemp=str(root / vtemp) if isinstance(vtemp, str) else "",
        contact=np.stack([left, right], -1),
        table_rotmat=t_rot, table_transl=t_tr, table_mesh=t_mesh,
        object_contact_codes=c_obj.astype(np.int8) if keep_vertex_contact else None,
    )


def list_sequence_files(root: str | Path, subjects: list[str] | None = None) -> list[Path]:
    """All ``grab/s*/…npz`` files of a dataset root, sorted, optionally for some subjects."""
    base = Path(root) / "grab"
    if not base.is_dir():
        raise FileNotFoundError(f"{root}: no 'grab/' folder (expected the GRAB root holding grab/ and tools/)")
    dirs = sorted(d for d in base.iterdir() if d.is_dir() and (subjects is None or d.name in subjects))
    return [f for d in dirs for f in sorted(d.glob("*.npz"))]


def split_files(root: str | Path, split: SplitConfig | None = None, part: str = "train",
                limit: int | None = None) -> list[Path]:
    """The sequence files of one split part, in a fixed order."""
    subjects = None if split is None or part == "all" else split.subjects(part)
    files = list_sequence_files(root, subjects)
    if split is not None and part != "all":
        files = [f for f in files if split.keeps(f.parent.name, f.stem)]
    return files if limit is None else files[:limit]


def load_dataset(
    root: str | Path, split: SplitConfig | None = None, part: str = "train", limit: int | None = None,
    progress: bool = False, keep_vertex_contact: bool = False,
) -> tuple[list[GrabSequence], LoadSummary]:
    """Load the files of one split part ('train'|'val'|'test'|'all'); bad files are skipped
    with a logged message and counted, never raised."""
    files = split_files(root, split, part, limit)
    summary = LoadSummary()
    seqs: list[GrabSequence] = []
    it = files
    if progress:
        from tqdm import tqdm

        it = tqdm(files, desc=f"reading {part}", unit="seq")
    for f in it:
        try:
            seqs.append(load_sequence(f, root, keep_vertex_contact=keep_vertex_contact))
            summary.loaded += 1
        except GrabFormatError as e:
            summary.skipped += 1
            summary.problems.append(str(e))
            log.warning("skipping %s", e)
    return seqs, summary
