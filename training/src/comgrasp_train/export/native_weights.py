"""Weights for the engine's native path (src/model/native): one ``.npy`` per tensor.

The ONNX graphs are what every runtime can run; the engine's hand-written kernels read the
same weights directly, by their PyTorch ``state_dict`` names, from ``<dir>/<name>.npy``.
A weight the exporter rounded to int8 (``weight_quant``) is stored as its int8 rows,
``<dir>/<name>.npy``, plus ``<dir>/<name>.scale.npy`` (float32 per row), so the native
GEMV reads a quarter of the bytes and computes the same ``q * scale`` values as the
graph's ``Cast * Mul``. The manifest section written beside the graph's
(``transformer.native`` / ``decoder.native``) lists every tensor's dtype and shape; the
engine checks each file against it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from ..weight_quant import QuantizedWeight


def write_native_weights(tensors: Mapping[str, torch.Tensor], root: str | Path, rel_dir: str,
                         quantized: Iterable[QuantizedWeight] = ()) -> dict:
    """Write ``tensors`` (name -> tensor, e.g. a filtered ``state_dict``) under
    ``root/rel_dir``; names found in ``quantized`` are written as int8 + scale. Returns the
    manifest section ``{"dir", "tensors": {name: {"dtype", "shape"}}}``."""
    q = {w.name: w for w in quantized}
    unknown = sorted(set(q) - set(tensors))
    if unknown:
        raise ValueError(f"int8 weights not among the tensors (names must be state_dict names): {unknown}")
    out = Path(root) / rel_dir
    out.mkdir(parents=True, exist_ok=True)
    listed = {}
    for name, t in tensors.items():
        if "/" in name or name.startswith("."):
            raise ValueError(f"tensor name {name!r} cannot be a file name")
        if name in q:
            w = q[name]
            if tuple(w.q.shape) != tuple(t.shape):
                raise ValueError(f"{name}: int8 shape {w.q.shape} differs from the tensor's {tuple(t.shape)}")
            if not np.array_equal(w.dequantized(), t.detach().cpu().float().numpy()):
                raise ValueError(f"{name}: the tensor is not the fake-quantized q * scale (quantize the model first)")
            np.save(out / f"{name}.npy", np.ascontiguousarray(w.q, dtype=np.int8))
            np.save(out / f"{name}.scale.npy", np.ascontiguousarray(w.scale, dtype=np.float32))
            listed[name] = {"dtype": "int8", "shape": [int(d) for d in w.q.shape]}
        else:
            a = t.detach().cpu().float().contiguous().numpy()
            np.save(out / f"{name}.npy", a)
            listed[name] = {"dtype": "float32", "shape": [int(d) for d in a.shape]}
    return {"dir": rel_dir, "tensors": listed}


def read_native_weights(root: str | Path, section: dict) -> dict[str, torch.Tensor]:
    """The float32 tensors back from a bundle (int8 ones dequantized), e.g. to rebuild the
    PyTorch model of a bundle: ``model.load_state_dict(read_native_weights(...))``."""
    base = Path(root) / section["dir"]
    out = {}
    for name, spec in section["tensors"].items():
        a = np.load(base / f"{name}.npy")
        if spec["dtype"] == "int8":
            scale = np.load(base / f"{name}.scale.npy")
            a = a.astype(np.float32) * scale.reshape((-1,) + (1,) * (a.ndim - 1))
        out[name] = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return out
