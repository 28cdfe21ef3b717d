"""int8 weight storage for exported graphs (the text encoder of the default bundle).

Weights are quantized per row (a Linear's output channel, an Embedding's token), symmetric,
``w ≈ q * s`` with ``q`` in [-127, 127]. The PyTorch module is *fake-quantized* in place
(its weights become exactly ``q * s`` in float32), so the model the GPT is trained with,
the parity vectors and the ONNX graph all compute the same function. In the ONNX file each
such weight is stored as an int8 tensor plus a float32 scale column and rebuilt by
``Cast(int8 -> float) * scale`` (two plain ops every runtime has; tract folds them into a
constant at load, except a result above 4 MiB such as the word-embedding table, which the
engine's text loader gathers before dequantizing). Arithmetic stays fp32: only the stored
weights are rounded.

A table can be rounded further to int4 per row (:func:`quantize_rows_int4`,
:func:`fake_quantize_rows_int4`): ``q`` in [-7, 7] with a per-row scale chosen to minimise
the squared rounding error. It stays a :class:`QuantizedWeight` with int8 ``q`` (``bits=4``),
so the ONNX file stores it exactly like an int8 weight; the engine's native weights pack it
two values a byte (``export/native_weights.py``). The default bundle's text encoder does
this to its word-embedding table only (``load_text_encoder(weights="int8-tok4")``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

# Smaller tensors (biases, LayerNorm, the token-type table) stay fp32: they cost nothing.
MIN_NUMEL = 4096


@dataclass(frozen=True)
class QuantizedWeight:
    name: str  # parameter name in the module
    q: np.ndarray  # (rows, ...) int8: a Linear/Embedding matrix or a Conv1d kernel
    scale: np.ndarray  # (rows,) float32
    bits: int = 8  # 4: q is in [-7, 7] (quantize_rows_int4), still stored as int8 here

    def dequantized(self) -> np.ndarray:
        return self.q.astype(np.float32) * self.scale.reshape((-1,) + (1,) * (self.q.ndim - 1))


def quantize_rows(w: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Per-row (first axis: output channel) symmetric int8 of a float tensor: (q int8 of the
    same shape, scale float32 per row). A zero row gets scale 1 (its q is 0), so
    dequantization never divides by zero."""
    w = w.detach().float().cpu().numpy()
    flat = w.reshape(w.shape[0], -1)
    amax = np.abs(flat).max(axis=1)
    scale = np.where(amax > 0, amax / 127.0, 1.0).astype(np.float32)
    q = np.clip(np.rint(flat / scale[:, None]), -127, 127).astype(np.int8).reshape(w.shape)
    return q, scale


# Fractions of the row's max |w| tried as the int4 clipping point (1.0: the plain amax scale).
INT4_FRACTIONS = np.linspace(0.5, 1.0, 21)
INT4_QMAX = 7


def quantize_rows_int4(w, fractions=INT4_FRACTIONS) -> tuple[np.ndarray, np.ndarray]:
    """Per-row symmetric int4 of a 2-D float tensor/array: (q int8 in [-7, 7] of the same
    shape, scale float32 per row). Each row tries ``scale = amax * f / 7`` for ``f`` in
    ``fractions`` (amax = the row's max |w|) and keeps the one with the smallest squared
    error of ``q * scale`` (the first on ties); a zero row gets scale 1, q 0."""
    if isinstance(w, torch.Tensor):
        w = w.detach().float().cpu().numpy()
    w = np.asarray(w, dtype=np.float32)
    if w.ndim != 2:
        raise ValueError(f"int4 rows need a 2-D table, got shape {w.shape}")
    amax = np.abs(w).max(axis=1)
    zero = amax == 0
    best_err = np.full(w.shape[0], np.inf)
    best_scale = np.ones(w.shape[0], dtype=np.float32)
    for f in fractions:
        scale = np.where(zero, 1.0, amax * np.float32(f) / np.float32(INT4_QMAX)).astype(np.float32)
        q = np.clip(np.rint(w / scale[:, None]), -INT4_QMAX, INT4_QMAX)
        err = ((q.astype(np.float32) * scale[:, None] - w).astype(np.float64) ** 2).sum(axis=1)
        better = err < best_err
        best_err = np.where(better, err, best_err)
        best_scale = np.where(better, scale, best_scale)
    q = np.clip(np.rint(w / best_scale[:, None]), -INT4_QMAX, INT4_QMAX).astype(np.int8)
    q[zero] = 0
    best_scale[zero] = 1.0
    return q, best_scale.astype(np.float32)


@torch.no_grad()
def fake_quantize_rows_int4(module: nn.Module, name: str, weights: list[QuantizedWeight] = (),
                            prefix: str = "") -> list[QuantizedWeight]:
    """Round the 2-D parameter ``name`` of ``module`` (e.g. ``embeddings.word_embeddings.weight``)
    to int4 per row (:func:`quantize_rows_int4`) in place: it becomes exactly ``q * scale`` in
    float32. Rounds the current values, so after :func:`fake_quantize_int8` it is the int8
    table that is re-rounded. Returns ``weights`` with the entry named ``prefix + name``
    replaced by (or, if absent, extended with) the int4 ``QuantizedWeight`` (``bits=4``)."""
    param = dict(module.named_parameters())[name]
    q, scale = quantize_rows_int4(param)
    qw = QuantizedWeight(f"{prefix}{name}", q, scale, bits=4)
    param.copy_(torch.from_numpy(qw.dequantized()).to(param))
    out = [w for w in weights if w.name != qw.name]
    at = next((i for i, w in enumerate(weights) if w.name == qw.name), len(out))
    out.insert(at, qw)
    return out


@torch.no_grad()
def fake_quantize_int8(module: nn.Module, min_numel: int = MIN_NUMEL, prefix: str = "") -> list[QuantizedWeight]:
    """Round every Linear/Embedding/Conv1d weight of ``module`` with at least ``min_numel``
    elements to int8 per output row, in place; returns what was quantized (for the ONNX
    rewrite), named ``prefix`` + the parameter name."""
    out = []
    for mod_name, mod in module.named_modules():
        if not isinstance(mod, (nn.Linear, nn.Embedding, nn.Conv1d)) or mod.weight.numel() < min_numel:
            continue
        q, scale = quantize_rows(mod.weight)
        qw = QuantizedWeight(f"{prefix}{mod_name}.weight", q, scale)
        mod.weight.copy_(torch.from_numpy(qw.dequantized()).to(mod.weight))
        out.append(qw)
    return out


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a, dtype=np.float32).tobytes()).hexdigest()


def store_int8_initializers(onnx_path: str | Path, weights: list[QuantizedWeight], *,
                            require_all: bool = True) -> dict:
    """Rewrite ``onnx_path`` in place: every float initializer equal (bit for bit) to a
    quantized weight or its transpose (the exporter folds Linear's transpose into the
    initializer) becomes int8 + scale + Cast + Mul. Returns a summary; with ``require_all``
    raises if a quantized weight was not found (the file would silently stay fp32); without
    it, weights the exporter folded into other constants stay fp32 and are counted."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.load(str(onnx_path))
    graph = model.graph
    # digest of the float32 bytes -> (weight, transposed?)
    wanted = {}
    for w in weights:
        deq = w.dequantized()
        wanted[(deq.shape, _digest(deq))] = (w, False)
        if deq.ndim == 2:
            wanted[(deq.T.shape, _digest(deq.T))] = (w, True)
    found: set[str] = set()
    new_inits, new_nodes = [], []
    for init in list(graph.initializer):
        if init.data_type != TensorProto.FLOAT or len(init.dims) < 2:
            continue
        arr = numpy_helper.to_array(init)
        hit = wanted.get((arr.shape, _digest(arr)))
        if hit is None:
            continue
        w, transposed = hit
        q = w.q.T if transposed else w.q
        scale = w.scale[None, :] if transposed else w.scale.reshape((-1,) + (1,) * (w.q.ndim - 1))
        name = init.name
        graph.initializer.remove(init)
        new_inits += [numpy_helper.from_array(np.ascontiguousarray(q), f"{name}__int8"),
                      numpy_helper.from_array(np.ascontiguousarray(scale, dtype=np.float32), f"{name}__scale")]
        new_nodes += [helper.make_node("Cast", [f"{name}__int8"], [f"{name}__f32"], to=TensorProto.FLOAT,
                                       name=f"{name}__dequant_cast"),
                      helper.make_node("Mul", [f"{name}__f32", f"{name}__scale"], [name], name=f"{name}__dequant_mul")]
        found.add(w.name)
    missing = sorted({w.name for w in weights} - found)
    if missing and require_all:
        raise RuntimeError(f"{onnx_path}: quantized weights not found among the initializers: {missing}")
    graph.initializer.extend(new_inits)
    # Dequantization first, so the node list stays topologically sorted.
    nodes = new_nodes + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(onnx_path))
    return {"scheme": "int8 per row, symmetric, q*scale via Cast+Mul; fp32 compute",
            "tensors": len(found), "int8_params": int(sum(w.q.size for w in weights if w.name in found)),
            "left_fp32": missing}
