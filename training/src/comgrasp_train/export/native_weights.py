"""Weights for the engine's native path (src/model/native): one ``.npy`` per tensor.

The ONNX graphs are what every runtime can run; the engine's hand-written kernels read the
same weights directly, by their PyTorch ``state_dict`` names, from ``<dir>/<name>.npy``.
A weight the exporter rounded to int8 (``weight_quant``) is stored as its int8 rows,
``<dir>/<name>.npy``, plus ``<dir>/<name>.scale.npy`` (float32 per row), so the native
GEMV reads a quarter of the bytes and computes the same ``q * scale`` values as the
graph's ``Cast * Mul``. A weight rounded to int4 (``QuantizedWeight.bits == 4``, q in
[-7, 7]; the default text encoder's word-embedding table) is packed two values a byte:
``<name>.npy`` is uint8 ``(rows, ceil(cols / 2))``, byte ``j`` of a row holding column ``2j``
in its low nibble and ``2j + 1`` in its high nibble, each nibble ``q + 8`` (an odd last
column's high nibble is 8, i.e. q = 0), plus the same ``<name>.scale.npy``; the manifest's
shape is the logical ``[rows, cols]``. The manifest section written beside the graph's
(``transformer.native`` / ``decoder.native`` / ``text_encoder.native``) lists every tensor's
dtype ("float32" | "int8" | "int4") and shape; the engine checks each file against it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from ..weight_quant import INT4_QMAX, QuantizedWeight

NATIVE_TEXT_DIR = "native/text"


def pack_int4(q: np.ndarray) -> np.ndarray:
    """(rows, cols) integers in [-7, 7] -> (rows, ceil(cols / 2)) uint8: column 2j in the low
    nibble of byte j, column 2j + 1 in its high nibble, each stored as q + 8 (an odd last
    column's high nibble is 8)."""
    q = np.asarray(q)
    if q.ndim != 2:
        raise ValueError(f"int4 packing needs a 2-D array, got shape {q.shape}")
    if q.size and (q.min() < -INT4_QMAX or q.max() > INT4_QMAX):
        raise ValueError(f"int4 values must be in [-{INT4_QMAX}, {INT4_QMAX}], got [{q.min()}, {q.max()}]")
    rows, cols = q.shape
    nib = np.full((rows, cols + cols % 2), 8, dtype=np.uint8)
    nib[:, :cols] = (q.astype(np.int16) + 8).astype(np.uint8)
    return np.ascontiguousarray(nib[:, 0::2] | (nib[:, 1::2] << 4))


def unpack_int4(packed: np.ndarray, cols: int) -> np.ndarray:
    """Inverse of :func:`pack_int4`: (rows, ceil(cols / 2)) uint8 -> (rows, cols) int8."""
    packed = np.asarray(packed)
    if packed.dtype != np.uint8 or packed.ndim != 2 or packed.shape[1] != (cols + 1) // 2:
        raise ValueError(f"packed int4 of {cols} columns must be uint8 (rows, {(cols + 1) // 2}), "
                         f"got {packed.dtype} {packed.shape}")
    nib = np.empty((packed.shape[0], 2 * packed.shape[1]), dtype=np.int8)
    nib[:, 0::2] = (packed & 0x0F).astype(np.int8) - 8
    nib[:, 1::2] = (packed >> 4).astype(np.int8) - 8
    return np.ascontiguousarray(nib[:, :cols])


def write_native_weights(tensors: Mapping[str, torch.Tensor], root: str | Path, rel_dir: str,
                         quantized: Iterable[QuantizedWeight] = ()) -> dict:
    """Write ``tensors`` (name -> tensor, e.g. a filtered ``state_dict``) under
    ``root/rel_dir``; names found in ``quantized`` are written as int8 + scale (int4, packed,
    + scale when the weight has ``bits == 4``). Returns the manifest section
    ``{"dir", "tensors": {name: {"dtype", "shape"}}}``."""
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
            if w.bits == 4:
                np.save(out / f"{name}.npy", pack_int4(w.q))
                dtype = "int4"
            elif w.bits == 8:
                np.save(out / f"{name}.npy", np.ascontiguousarray(w.q, dtype=np.int8))
                dtype = "int8"
            else:
                raise ValueError(f"{name}: no native storage for {w.bits}-bit weights")
            np.save(out / f"{name}.scale.npy", np.ascontiguousarray(w.scale, dtype=np.float32))
            listed[name] = {"dtype": dtype, "shape": [int(d) for d in w.q.shape]}
        else:
            a = t.detach().cpu().float().contiguous().numpy()
            np.save(out / f"{name}.npy", a)
            listed[name] = {"dtype": "float32", "shape": [int(d) for d in a.shape]}
    return {"dir": rel_dir, "tensors": listed}


def read_native_weights(root: str | Path, section: dict) -> dict[str, torch.Tensor]:
    """The float32 tensors back from a bundle (int8 and int4 ones dequantized), e.g. to
    rebuild the PyTorch model of a bundle: ``model.load_state_dict(read_native_weights(...))``."""
    base = Path(root) / section["dir"]
    out = {}
    for name, spec in section["tensors"].items():
        a = np.load(base / f"{name}.npy")
        if spec["dtype"] == "int4":
            if len(spec["shape"]) != 2:
                raise ValueError(f"{name}: int4 tensors are 2-D, the manifest says {spec['shape']}")
            a = unpack_int4(a, int(spec["shape"][1]))
        if spec["dtype"] in ("int8", "int4"):
            scale = np.load(base / f"{name}.scale.npy")
            a = a.astype(np.float32) * scale.reshape((-1,) + (1,) * (a.ndim - 1))
        out[name] = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    return out


def bert_native_names(n_layers: int) -> list[str]:
    """The tensors of ``text_encoder.native``: ``BertTokenStates``' parameter names, in order."""
    names = [f"embeddings.{n}" for n in ("word_embeddings.weight", "position_embeddings.weight",
                                         "token_type_embeddings.weight", "LayerNorm.weight", "LayerNorm.bias")]
    for i in range(n_layers):
        for sub in ("attention.self.query", "attention.self.key", "attention.self.value",
                    "attention.output.dense", "attention.output.LayerNorm", "intermediate.dense",
                    "output.dense", "output.LayerNorm"):
            names += [f"layers.{i}.{sub}.weight", f"layers.{i}.{sub}.bias"]
    return names


def write_native_text(encoder, root: str | Path, rel_dir: str = NATIVE_TEXT_DIR) -> dict:
    """The ``text_encoder.native`` section of a BERT (MiniLM-kind) encoder, its files under
    ``root/rel_dir``: ``{"dir", "heads", "layer_norm_eps", "activation", "tensors"}`` with
    every parameter of ``BertTokenStates`` (no buffers). Linear weights and the word table
    as the encoder's rounded weights (``encoder.int8_weights``: int8, the word table int4
    under "int8-tok4"), fp32 where the encoder is not rounded; the position table only its
    first ``max_tokens`` rows, float32 (the values the network uses, rounded or not); the
    token-type table, LayerNorms and biases float32."""
    from ..text_encoder import BertTokenStates

    net = encoder.network
    if not isinstance(net, BertTokenStates):
        raise ValueError(f"native text weights exist for BERT (minilm-kind) encoders only, not {encoder.kind!r}")
    cfg = encoder.hf_model.config
    act = getattr(cfg, "hidden_act", None)
    if act != "gelu":
        raise ValueError(f"the native text encoder computes the exact (erf) GELU; this BERT's hidden_act is {act!r}")
    if getattr(cfg, "position_embedding_type", "absolute") != "absolute":
        raise ValueError(f"the native text encoder needs absolute position embeddings, "
                         f"not {cfg.position_embedding_type!r}")
    params = dict(net.named_parameters())
    names = bert_native_names(len(net.layers))
    if set(params) != set(names):
        raise ValueError(f"unexpected BERT parameters: missing {sorted(set(names) - set(params))[:3]}, "
                         f"extra {sorted(set(params) - set(names))[:3]}")
    pos = "embeddings.position_embeddings.weight"
    tensors = {n: params[n].detach() for n in names}
    tensors[pos] = tensors[pos][: encoder.max_tokens].clone()
    q = [w for w in encoder.int8_weights if w.name in tensors and w.name != pos]
    for w in q:
        if w.bits == 4 and w.name != "embeddings.word_embeddings.weight":
            raise ValueError(f"{w.name}: only the word-embedding table may be int4")
    sec = write_native_weights(tensors, root, rel_dir, quantized=q)
    return {"dir": sec["dir"], "heads": int(cfg.num_attention_heads), "layer_norm_eps": float(cfg.layer_norm_eps),
            "activation": "gelu", "tensors": sec["tensors"]}
