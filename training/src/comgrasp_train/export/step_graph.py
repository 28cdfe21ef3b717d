"""ONNX export of one decode step of the four coordinated Transformers (DESIGN §4).

The graph is the network only (no sampling, no cache bookkeeping), with static
shapes for tract: batch B fixed at export, cache of S = block_size slots (L_max + 2).
The caller (the Rust engine, or `OnnxStepRunner` here) owns the cache, zero-fills it,
and after each step writes the returned rows at slot `pos`. One graph serves the
condition step (pos = 0: the text embedding is projected into the condition token,
`tokens` is ignored) and every token step (pos >= 1: `tokens` are the codes of step
pos - 1, `text_emb` is ignored but must still be fed).

Inputs, in this order (per stream s in global, body, lhand, rhand; L = n_layers,
H = n_heads, D_s = width_s / H):

    tokens        int64   (B, 4)           valid ids (< V_s) also at pos 0 (e.g. Pad)
    pos           int64   (1,)             0 <= pos <= block_size - 1, shared by the batch
    text_emb      float32 (B, d_text)
    cache_k_<s>   float32 (L, B, H, S, D_s) slots < pos filled, the rest finite (zeros)
    cache_v_<s>   float32 (L, B, H, S, D_s)     (k then v, stream by stream)

Outputs, in this order:

    logits_<s>    float32 (B, V_s)          for the 4 streams, V_s = codebook + 2
    new_k_<s>     float32 (L, B, H, 1, D_s) row for slot pos: cache_k_<s>[:, :, :, pos] = new_k_<s>[:, :, :, 0]
    new_v_<s>     float32 (L, B, H, 1, D_s)     (k then v, stream by stream)
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..models.gpt_configs import STREAMS, TransformerConfig
from ..models.transformer import ComGraspTransformer

OPSET = 17
# Ops the graph must not contain: scatters and anything making shapes dynamic.
FORBIDDEN_OPS = frozenset({"ScatterND", "ScatterElements", "Scatter", "Shape", "ConstantOfShape",
                           "NonZero", "Loop", "If", "Range", "Expand"})


def input_names() -> list[str]:
    return ["tokens", "pos", "text_emb"] + [f"cache_{kv}_{s}" for s in STREAMS for kv in "kv"]


def output_names() -> list[str]:
    return [f"logits_{s}" for s in STREAMS] + [f"new_{kv}_{s}" for s in STREAMS for kv in "kv"]


def io_spec(cfg: TransformerConfig, batch: int = 1) -> dict[str, list[tuple[str, str, tuple]]]:
    """(name, dtype, shape) of every input and output, in graph order."""
    L, H, S = cfg.n_layers, cfg.n_heads, cfg.block_size
    cache = [(f"cache_{kv}_{s}", "float32", (L, batch, H, S, d))
             for s, d in zip(STREAMS, cfg.head_dims) for kv in "kv"]
    rows = [(f"new_{kv}_{s}", "float32", (L, batch, H, 1, d))
            for s, d in zip(STREAMS, cfg.head_dims) for kv in "kv"]
    return {
        "inputs": [("tokens", "int64", (batch, len(STREAMS))), ("pos", "int64", (1,)),
                   ("text_emb", "float32", (batch, cfg.d_text))] + cache,
        "outputs": [(f"logits_{s}", "float32", (batch, v))
                    for s, v in zip(STREAMS, cfg.vocab_sizes)] + rows,
    }


class StepGraph(nn.Module):
    """Flat-argument wrapper of `ComGraspTransformer.step` for tracing."""

    def __init__(self, model: ComGraspTransformer):
        super().__init__()
        self.model = model

    def forward(self, tokens, pos, text_emb, *caches):
        logits, new_k, new_v = self.model.step(tokens, pos, text_emb, list(caches[0::2]),
                                               list(caches[1::2]))
        return (*logits, *[t for kv in zip(new_k, new_v) for t in kv])


def example_inputs(cfg: TransformerConfig, batch: int = 1, pos: int = 1) -> tuple[torch.Tensor, ...]:
    """Zero caches, Pad tokens: valid inputs of the right dtypes and shapes."""
    shapes = io_spec(cfg, batch)["inputs"]
    return (torch.tensor(cfg.pad_ids).expand(batch, len(STREAMS)).contiguous(),
            torch.tensor([pos]),
            torch.zeros(shapes[2][2]),
            *[torch.zeros(shape) for _, _, shape in shapes[3:]])


def export_step_onnx(model: ComGraspTransformer, path: str | Path, batch: int = 1) -> dict:
    """Write the step graph (opset 17, static shapes) and return its `io_spec`.

    Exports a CPU float32 eval copy, so the caller's model is left untouched. Raises if
    the graph contains any of FORBIDDEN_OPS.
    """
    import onnx

    cfg = model.cfg
    net = StepGraph(copy.deepcopy(model).cpu().float().eval())
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The TorchScript exporter (deprecated in torch >= 2.9, hence the silenced warning)
    # is used on purpose: it needs no onnxscript and traces a plain static graph.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(net, example_inputs(cfg, batch), str(path), dynamo=False,
                          input_names=input_names(), output_names=output_names(),
                          opset_version=OPSET, do_constant_folding=True)
    bad = sorted({n.op_type for n in onnx.load(str(path), load_external_data=False).graph.node}
                 & FORBIDDEN_OPS)
    if bad:
        raise RuntimeError(f"step graph contains ops unsuitable for tract: {bad}")
    return io_spec(cfg, batch)


class OnnxStepRunner:
    """Drives an exported step graph with onnxruntime the way the engine does with
    tract: owns the fixed cache, feeds one step, writes the returned rows at `pos`.
    Its `step_fn` plugs into `sampling.run_sampling_loop` (parity, benchmarks)."""

    def __init__(self, path: str | Path, cfg: TransformerConfig, text_emb: np.ndarray,
                 threads: int = 1):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        self.cfg = cfg
        self.text_emb = np.ascontiguousarray(text_emb, dtype=np.float32)
        batch = self.text_emb.shape[0]
        self.cache = {name: np.zeros(shape, dtype=np.float32)
                      for name, _, shape in io_spec(cfg, batch)["inputs"][3:]}
        self.n_streams = len(STREAMS)

    def step_fn(self, tokens: np.ndarray, pos: int) -> list[np.ndarray]:
        feeds = {"tokens": np.ascontiguousarray(tokens, dtype=np.int64),
                 "pos": np.array([pos], dtype=np.int64), "text_emb": self.text_emb, **self.cache}
        out = self.session.run(None, feeds)
        for name, row in zip(self.cache, out[self.n_streams:]):
            self.cache[name][:, :, :, pos] = row[:, :, :, 0]
        return out[: self.n_streams]
