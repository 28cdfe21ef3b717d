"""ONNX export of the streaming VQ decoder step (``models.streaming.DecoderStep``) and an
onnxruntime driver that runs it the way the engine runs it in tract.

The graph is the network only, static shapes, batch B fixed at export (1 in a bundle),
P = 4 components, K = the decoder's context in tokens, F = frames per token:

    inputs   state       int64   (B, P, K-1)  ids of the previous K-1 tokens, oldest first;
                                              initially every slot = the component's
                                              codebook size (the decoder's "before the
                                              start" id, see ``initial_state``)
             tokens      int64   (B, P)       the newest code of every component (< codebook)
    outputs  frames      float32 (B, F, 335)  normalized features of that token's F frames;
                                              the contact channels (240, 334) are already
                                              probabilities (sigmoid inside the graph)
             next_state  int64   (B, P, K-1)  feed back as ``state`` for the next token

Chunk by chunk this equals the offline decode of the whole sequence (DESIGN §3 deviation 1);
``check_decoder_onnx`` measures that for the exported graph (the bundle exporter raises on
a mismatch).

The traced graph computes its static shapes with Shape/ConstantOfShape/Range/Gather chains
(from ``F.pad``, ``torch.arange`` and ``x.shape`` in the layers). ``simplify`` folds them
away with onnxruntime's *basic* offline optimizations (constant folding and standard-op
fusions only, so the file stays plain ONNX) and drops the opset imports no node uses: a
smaller graph with fewer ops for tract to get wrong.
"""

from __future__ import annotations

import copy
import warnings
from pathlib import Path

import numpy as np
import torch

from ..layout import FRAME_DIM
from ..models.streaming import DecoderStep
from ..models.vqvae import ComponentVQ

OPSET = 17
INPUT_NAMES = ("state", "tokens")
OUTPUT_NAMES = ("frames", "next_state")
# Dynamic control flow, scatters and resampling have no place in a static conv/attention stack.
FORBIDDEN_OPS = frozenset({"ScatterND", "ScatterElements", "Scatter", "NonZero", "Loop", "If", "Resize"})
# Static-shape arithmetic that ``simplify`` must have folded away.
SHAPE_OPS = frozenset({"Shape", "ConstantOfShape", "Range"})
STREAM_TOLERANCE = 1e-4  # DESIGN §3: chunked == offline decoding on normalized features


def io_spec(vq: ComponentVQ, batch: int = 1) -> dict[str, list[tuple[str, str, tuple]]]:
    """(name, dtype, shape) of every input and output, in graph order."""
    p, k1, f = len(vq.parts), vq.context_tokens - 1, vq.frames_per_token
    return {
        "inputs": [("state", "int64", (batch, p, k1)), ("tokens", "int64", (batch, p))],
        "outputs": [("frames", "float32", (batch, f, FRAME_DIM)), ("next_state", "int64", (batch, p, k1))],
    }


def initial_state(vq: ComponentVQ, batch: int = 1) -> np.ndarray:
    """(B, P, K-1) int64: every slot holds the component's pad id (its codebook size)."""
    return DecoderStep(vq).initial_state(batch).cpu().numpy()


def export_decoder_onnx(vq: ComponentVQ, path: str | Path, batch: int = 1, simplify: bool = True) -> dict:
    """Write the decoder step graph (opset 17, static shapes) and return its ``io_spec``.

    Exports a CPU float32 eval copy (the caller's model is untouched). Raises if the graph
    contains FORBIDDEN_OPS (or, simplified, SHAPE_OPS).
    """
    import onnx

    step = DecoderStep(copy.deepcopy(vq).cpu().float().eval()).eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    args = (step.initial_state(batch), torch.zeros(batch, len(vq.parts), dtype=torch.long))
    # TorchScript exporter on purpose (no onnxscript, plain static graph); see step_graph.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(step, args, str(path), dynamo=False, input_names=list(INPUT_NAMES),
                          output_names=list(OUTPUT_NAMES), opset_version=OPSET, do_constant_folding=True)
    if simplify:
        simplify_onnx(path)
    forbidden = FORBIDDEN_OPS | SHAPE_OPS if simplify else FORBIDDEN_OPS
    bad = sorted({n.op_type for n in onnx.load(str(path)).graph.node} & forbidden)
    if bad:
        raise RuntimeError(f"decoder graph contains ops unsuitable for tract: {bad}")
    return io_spec(vq, batch)


def simplify_onnx(path: str | Path) -> None:
    """Fold static shape arithmetic in place (onnxruntime basic level; see module doc)."""
    import onnx
    import onnxruntime as ort

    path = Path(path)
    tmp = path.with_name(path.name + ".simplified")
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    opts.optimized_model_filepath = str(tmp)
    ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    model = onnx.load(str(tmp))
    used = {n.domain for n in model.graph.node} | {""}
    keep = [o for o in model.opset_import if o.domain in used]
    del model.opset_import[:]
    model.opset_import.extend(keep)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    tmp.unlink()


def check_decoder_onnx(vq: ComponentVQ, path: str | Path, tokens: np.ndarray
                       ) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """Decode ``tokens`` (B, P, N) three ways: PyTorch offline (whole sequence), PyTorch
    streaming step, the ONNX graph step by step (onnxruntime). Returns the max abs
    differences {stream_vs_offline, onnx_vs_torch} and the (B, N*F, 335) normalized frames
    {offline, stream, onnx}."""
    from ..models.streaming import StreamingDecoder

    t = torch.as_tensor(np.asarray(tokens, dtype=np.int64))
    vq = copy.deepcopy(vq).cpu().float().eval()
    with torch.no_grad():
        offline = vq.decode(t).numpy()
    sd = StreamingDecoder(vq, batch_size=t.shape[0])
    stream = np.concatenate([sd.step(t[:, :, i]).numpy() for i in range(t.shape[-1])], 1)
    got = OnnxDecoderRunner(path, initial_state(vq, t.shape[0])).decode(t.numpy())
    diffs = {"stream_vs_offline": float(np.abs(stream - offline).max()),
             "onnx_vs_torch": float(np.abs(got - stream).max())}
    return diffs, {"offline": offline, "stream": stream, "onnx": got}


class OnnxDecoderRunner:
    """Feeds an exported decoder graph one token step at a time, keeping the state.
    ``initial`` is the (B, P, K-1) state of a new sequence (``initial_state`` or the
    manifest's ``decoder.initial_state``)."""

    def __init__(self, path: str | Path, initial, threads: int = 1):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        self.initial = np.asarray(initial, dtype=np.int64)
        self.reset()

    def reset(self) -> None:
        self.state = self.initial.copy()

    def step(self, tokens: np.ndarray) -> np.ndarray:
        """tokens (B, P) int64 -> frames (B, F, 335) float32."""
        frames, self.state = self.session.run(
            None, {"state": self.state, "tokens": np.ascontiguousarray(tokens, dtype=np.int64)})
        return frames

    def decode(self, tokens: np.ndarray) -> np.ndarray:
        """tokens (B, P, N) -> (B, N * F, 335), from the initial state."""
        self.reset()
        return np.concatenate([self.step(tokens[:, :, i]) for i in range(tokens.shape[-1])], 1)
