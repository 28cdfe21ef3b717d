"""The GRAB sequence file format: constants and a writer.

A GRAB file is an ``.npz`` whose every entry is a 0-d array (nested dicts pickled as
objects), 120 fps, z-up metres; object and table rotations are axis-angle used in GRAB's
ROW-vector convention ``v_world = v @ R + t`` with ``R = rodrigues(global_orient)``
(reference §1). The writer is used by SynthGrasp and by the tests' fixtures, so both are
read by exactly the reader that reads a user's GRAB download.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

GRAB_FPS = 120
N_COMPS = 24  # MANO PCA components in GRAB's files
LEFT_HAND_CODES = frozenset({21, *range(26, 41)})
RIGHT_HAND_CODES = frozenset({22, *range(41, 56)})

TOP_LEVEL_KEYS = ("gender", "sbj_id", "obj_name", "motion_intent", "framerate", "n_frames",
                  "n_comps", "body", "lhand", "rhand", "object", "table", "contact")


def body_params_from_fullpose(fullpose: np.ndarray, transl: np.ndarray) -> dict:
    """GRAB's ``body/params`` dict from a (T, 165) fullpose. The PCA hand coefficients
    cannot be made without the MANO basis, so they are written as zeros; every consumer
    (and our reader) uses ``fullpose`` for the hands."""
    T = fullpose.shape[0]
    f = fullpose.astype(np.float32)
    return {
        "transl": transl.astype(np.float32),
        "global_orient": f[:, 0:3],
        "body_pose": f[:, 3:66],
        "jaw_pose": f[:, 66:69],
        "leye_pose": f[:, 69:72],
        "reye_pose": f[:, 72:75],
        "left_hand_pose": np.zeros((T, N_COMPS), np.float32),
        "right_hand_pose": np.zeros((T, N_COMPS), np.float32),
        "expression": np.zeros((T, 10), np.float32),
        "fullpose": f,
    }


def write_grab_npz(
    path: str | Path,
    *,
    gender: str,
    sbj_id: str,
    obj_name: str,
    motion_intent: str,
    fullpose: np.ndarray,
    transl: np.ndarray,
    object_transl: np.ndarray,
    object_global_orient: np.ndarray,
    table_transl: np.ndarray,
    table_global_orient: np.ndarray,
    contact_body: np.ndarray,
    contact_object: np.ndarray,
    vtemp: str,
    object_mesh: str,
    table_mesh: str = "tools/object_meshes/contact_meshes/table.ply",
    lhand: dict | None = None,
    rhand: dict | None = None,
    framerate: int = GRAB_FPS,
    compress: bool = True,
) -> Path:
    """Write one sequence in GRAB's layout. Rotations are axis-angle (GRAB conventions);
    mesh paths are relative to the dataset root, as in GRAB."""
    T = int(fullpose.shape[0])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sid_vt = vtemp[: -len(".ply")] if vtemp.endswith(".ply") else vtemp

    def hand(d: dict | None, side: str) -> dict:
        d = d or {}
        params = {
            "global_orient": np.asarray(d.get("global_orient", np.zeros((T, 3))), np.float32),
            "hand_pose": np.zeros((T, N_COMPS), np.float32),
            "transl": np.asarray(d.get("transl", np.zeros((T, 3))), np.float32),
            "fullpose": np.asarray(d.get("fullpose", np.zeros((T, 45))), np.float32),
        }
        return {"params": params, "vtemp": f"{sid_vt}_{side}.ply"}

    entries = {
        "gender": np.array(gender),
        "sbj_id": np.array(sbj_id),
        "obj_name": np.array(obj_name),
        "motion_intent": np.array(motion_intent),
        "framerate": np.array(framerate),
        "n_frames": np.array(T),
        "n_comps": np.array(N_COMPS),
        "body": np.array({"params": body_params_from_fullpose(fullpose, transl), "vtemp": vtemp}, dtype=object),
        "lhand": np.array(hand(lhand, "lhand"), dtype=object),
        "rhand": np.array(hand(rhand, "rhand"), dtype=object),
        "object": np.array(
            {"params": {"transl": object_transl.astype(np.float32),
                        "global_orient": object_global_orient.astype(np.float32)},
             "object_mesh": object_mesh}, dtype=object),
        "table": np.array(
            {"params": {"transl": table_transl.astype(np.float32),
                        "global_orient": table_global_orient.astype(np.float32)},
             "table_mesh": table_mesh}, dtype=object),
        "contact": np.array({"body": contact_body.astype(np.int8), "object": contact_object.astype(np.int8)},
                            dtype=object),
    }
    _savez_reproducible(path, entries, compress)
    return path


def _savez_reproducible(path: Path, entries: dict, compress: bool) -> None:
    """``np.savez(_compressed)`` with a fixed zip timestamp per entry, so that equal content
    gives byte-identical files (numpy stamps each entry with the current time). Deflate
    level 1: the (T, points) contact arrays are mostly zeros, so it is ~1.5x faster than
    the default level for files ~29% larger, and compressing was a quarter of SynthGrasp's
    generation time."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=method, allowZip64=True) as zf:
        for key, value in entries.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o600 << 16
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=True)
            zf.writestr(info, buf.getbuffer(), compresslevel=1 if compress else None)
