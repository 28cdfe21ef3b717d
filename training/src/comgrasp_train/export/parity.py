"""Parity vectors of a bundle: what PyTorch computed, for the engine's tests to replay.

Everything lives under ``parity/`` as ``.npy`` files (little-endian, C order) described by
``parity/index.json``:

    {"format": "comgrasp-parity", "version": 1,
     "files": [{"path": "parity/step/case0_tokens.npy", "dtype": "int64", "shape": [7, 4],
                "tolerance": 0.0, "what": "..."}, ...],      # tolerance: max abs diff, 0 = exact
     "text":   {"cases": "parity/text/cases.json"},          # written by export_text_encoder
     "step":   [{"prompt", "seed", "sampling", "length", "greedy_length", "logit_steps", "guided", "files"}],
     "decode": [{"from_step_case", "n_tokens", "files"}],
     "rng":    {"seed", "files"}}

Paths are relative to the bundle root (the keys of the manifest's ``files`` table).

* text (``parity/text/``, by ``export_text_encoder``): ids/mask/type/position ids (exact),
  token states (1e-4 on real tokens), pooled embedding (1e-5).
* step, per prompt: ``text_emb`` (1, d_text), the embedding fed to the step graph;
  ``logits_<stream>`` (n, V_s): the logits of steps 0..n-1 from the teacher-forced PyTorch
  forward over the sampled codes (n = min(N, length + 1)); ``tokens`` (length, 4): the codes
  sampled with the bundle's default sampling params and seed (with a default guidance other
  than 1, from guided logits, not from ``logits_<stream>`` alone); ``greedy_tokens``: the same
  with temperature 0; ``guided_greedy_tokens``: temperature 0 with classifier-free guidance
  at ``GUIDED_PARITY_SCALE`` (the case's ``guided``: scale and length). Lengths are in the case entry.
* decode: ``tokens`` (n, 4) of step case 0 -> ``frames_offline`` (n*F, 335) normalized,
  from ``ComponentVQ.decode`` of the whole sequence; ``frames_stream`` (n*F, 335) from the
  PyTorch streaming step, token by token; ``frames_denormalized`` = frames_offline * std +
  mean (contact channels stay probabilities).
* rng: ``u64`` (8,) uint64 and ``uniform`` (8,) float64: the first SplitMix64 outputs for the
  default seed (the sampler's random numbers, DESIGN §4).

At export every graph is also run in onnxruntime and checked against PyTorch (tokens must
be identical; logits/frames within the tolerances): a mismatch raises ``ParityError``.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..models.gpt_configs import STREAMS
from ..models.sampling import SamplingParams, SplitMix64, generate, guide_logits, run_sampling_loop
from .decoder_graph import STREAM_TOLERANCE, check_decoder_onnx
from .step_graph import OnnxStepRunner

INDEX = "parity/index.json"
TOL_EMBEDDING = 1e-5
TOL_STATES = 1e-4
TOL_LOGITS = 1e-4
TOL_FRAMES = STREAM_TOLERANCE
DEFAULT_STEP_PROMPTS: tuple[str, ...] = ("A woman drinks from the mug.", "The man lifts a small cube.")
# The classifier-free guidance scale of the guided greedy parity case, whatever the bundle's default.
GUIDED_PARITY_SCALE = 2.0


class ParityError(RuntimeError):
    """An exported graph disagrees with PyTorch."""


class ParityWriter:
    """Saves arrays under the bundle root and collects their index entries."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.files: list[dict] = []

    def add(self, rel: str, array: np.ndarray, tolerance: float, what: str) -> str:
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        array = np.ascontiguousarray(array)
        np.save(path, array)
        self.files.append({"path": rel, "dtype": str(array.dtype), "shape": list(array.shape),
                           "tolerance": float(tolerance), "what": what})
        return rel

    def index_existing(self, rel: str, tolerance: float, what: str) -> str:
        """Index a .npy somebody else wrote (the text parity files)."""
        a = np.load(self.root / rel, mmap_mode="r")
        self.files.append({"path": rel, "dtype": str(a.dtype), "shape": list(a.shape),
                           "tolerance": float(tolerance), "what": what})
        return rel


def index_text_parity(w: ParityWriter, text_dir: str = "parity/text") -> dict:
    """Add the files of ``export_text_encoder``'s parity/text/cases.json to the index."""
    doc = json.loads((w.root / text_dir / "cases.json").read_text(encoding="utf-8"))
    for k, case in enumerate(doc["cases"]):
        for role, name in case["files"].items():
            if role == "embedding":
                tol, what = TOL_EMBEDDING, f"text case {k}: pooled, L2-normalized embedding (PyTorch)"
            elif role in ("input_ids", "attention_mask", "token_type_ids", "position_ids"):
                tol, what = 0.0, f"text case {k}: text_encoder.onnx input {role}"
            else:
                tol, what = TOL_STATES, f"text case {k}: text_encoder.onnx output {role} (compare real tokens only)"
            w.index_existing(f"{text_dir}/{name}", tol, what)
    return {"cases": f"{text_dir}/cases.json"}


def _teacher_forced_logits(gpt, emb: torch.Tensor, tokens: torch.Tensor, n: int) -> list[np.ndarray]:
    """Logits of steps 0..n-1 given the codes of steps 0..n-2 (one forward pass)."""
    with torch.no_grad():
        out = gpt.eval()(emb, tokens[:, : n - 1])
    return [lg[0, :n].float().cpu().numpy() for lg in out]


def _onnx_generation(step_path, cfg, emb: np.ndarray, params: SamplingParams, seed: int, n: int):
    """Generate through the ONNX step graph (guided: a second runner on the null
    condition, as the engine does); also return the logits of its first n steps."""
    runner = OnnxStepRunner(step_path, cfg, emb)
    null = OnnxStepRunner(step_path, cfg, np.zeros_like(emb)) if params.guidance != 1.0 else None
    seen: list[list[np.ndarray]] = []

    def step_fn(tokens, k):
        out = runner.step_fn(tokens, k)
        if k < n:  # the graph's own logits, compared with the teacher-forced forward
            seen.append([o[0] for o in out])
        if null is not None:
            out = [guide_logits(c, u, params.guidance) for c, u in zip(out, null.step_fn(tokens, k))]
        return out

    gen = run_sampling_loop(step_fn, cfg, 1, params, [seed])
    return gen, [np.stack([s[i] for s in seen]) for i in range(len(STREAMS))] if seen else []


def write_step_parity(w: ParityWriter, gpt, encoder, step_path: str | Path, params: SamplingParams,
                      seed: int, prompts: Sequence[str] = DEFAULT_STEP_PROMPTS,
                      n_logit_steps: int = 5) -> tuple[list[dict], dict, list[np.ndarray]]:
    """Step cases (see module doc) from a CPU float32 ``gpt``. Returns (cases, measured
    diffs, per-case sampled codes (length, 4))."""
    cfg = gpt.cfg
    # greedy: unguided; guided: greedy at GUIDED_PARITY_SCALE
    greedy = SamplingParams(0.0, 0, params.min_len, params.max_len)
    guided = replace(greedy, guidance=GUIDED_PARITY_SCALE)
    cases, codes, max_logit = [], [], 0.0
    for k, prompt in enumerate(prompts):
        emb = encoder.encode([prompt]).to(torch.float32).cpu()
        gen = generate(gpt, emb, params, seed=seed)
        ref_greedy = generate(gpt, emb, greedy, seed=seed)
        ref_guided = generate(gpt, emb, guided, seed=seed)
        length = int(gen.lengths[0])
        n = min(n_logit_steps, length + 1)
        logits = _teacher_forced_logits(gpt, emb, gen.tokens, n)
        onnx_gen, onnx_logits = _onnx_generation(step_path, cfg, emb.numpy(), params, seed, n)
        onnx_greedy, _ = _onnx_generation(step_path, cfg, emb.numpy(), greedy, seed, 0)
        onnx_guided, _ = _onnx_generation(step_path, cfg, emb.numpy(), guided, seed, 0)
        for name, ref, got in (("sampled", gen, onnx_gen), ("greedy", ref_greedy, onnx_greedy),
                               ("guided greedy", ref_guided, onnx_guided)):
            if not (torch.equal(ref.lengths, got.lengths) and torch.equal(ref.tokens, got.tokens)):
                raise ParityError(f"step.onnx gives other {name} tokens than PyTorch for {prompt!r} "
                                  f"(lengths {got.lengths.tolist()} vs {ref.lengths.tolist()})")
        diff = max(float(np.abs(a - b).max()) for a, b in zip(onnx_logits, logits))
        if diff > TOL_LOGITS:
            raise ParityError(f"step.onnx logits differ from PyTorch by {diff:.3g} > {TOL_LOGITS} for {prompt!r}")
        max_logit = max(max_logit, diff)
        d = f"parity/step/case{k}"
        files = {"text_emb": w.add(f"{d}_text_emb.npy", emb.numpy(), TOL_EMBEDDING,
                                   f"step case {k}: text embedding fed to step.onnx (prompt {prompt!r})")}
        for s, lg in zip(STREAMS, logits):
            files[f"logits_{s}"] = w.add(f"{d}_logits_{s}.npy", lg, TOL_LOGITS,
                                         f"step case {k}: logits_{s} of steps 0..{n - 1} (teacher-forced with tokens)")
        seq = gen.tokens[0, :length].numpy().astype(np.int64).reshape(length, len(STREAMS))
        gseq = ref_greedy.tokens[0, : int(ref_greedy.lengths[0])].numpy().astype(np.int64)
        files["tokens"] = w.add(f"{d}_tokens.npy", seq, 0.0,
                                f"step case {k}: codes sampled with the default sampling params, seed {seed}")
        files["greedy_tokens"] = w.add(f"{d}_greedy_tokens.npy", gseq.reshape(-1, len(STREAMS)), 0.0,
                                       f"step case {k}: codes with temperature 0 (greedy)")
        guided_len = int(ref_guided.lengths[0])
        files["guided_greedy_tokens"] = w.add(
            f"{d}_guided_greedy_tokens.npy", ref_guided.tokens[0, :guided_len].numpy().astype(np.int64).reshape(-1, 4),
            0.0, f"step case {k}: codes with temperature 0 and classifier-free guidance {GUIDED_PARITY_SCALE}")
        cases.append({"prompt": prompt, "seed": int(seed), "sampling": sampling_dict(params, cfg.l_max),
                      "length": length, "greedy_length": int(ref_greedy.lengths[0]), "logit_steps": n,
                      "guided": {"scale": GUIDED_PARITY_SCALE, "length": guided_len}, "files": files})
        codes.append(seq)
    return cases, {"step_logits": max_logit}, codes


def write_decode_parity(w: ParityWriter, vq, decoder_path: str | Path, normalizer, codes: Sequence[np.ndarray]
                        ) -> tuple[list[dict], dict]:
    """Decode case from the first non-empty generation (see module doc)."""
    k = next((i for i, c in enumerate(codes) if len(c)), None)
    if k is None:
        raise ParityError("every parity generation is empty (End at step 0); use sampling min_len >= 1")
    seq = codes[k]  # (n, P)
    tokens = seq.T[None]  # (1, P, n)
    diffs, frames = check_decoder_onnx(vq, decoder_path, tokens)
    if diffs["stream_vs_offline"] > TOL_FRAMES:
        raise ParityError(f"streaming decode differs from offline decode by "
                          f"{diffs['stream_vs_offline']:.3g} > {TOL_FRAMES}")
    if diffs["onnx_vs_torch"] > TOL_FRAMES:
        raise ParityError(f"decoder.onnx differs from PyTorch by {diffs['onnx_vs_torch']:.3g} > {TOL_FRAMES}")
    offline, stream = frames["offline"][0], frames["stream"][0]
    denorm = normalizer.denormalize(offline.astype(np.float32))
    d = "parity/decode/case0"
    tol_denorm = TOL_FRAMES * max(1.0, float(np.max(normalizer.std)))
    files = {
        "tokens": w.add(f"{d}_tokens.npy", seq, 0.0, f"decode case 0: the codes of step case {k}, (n, 4)"),
        "frames_offline": w.add(f"{d}_frames_offline.npy", offline, TOL_FRAMES,
                                "decode case 0: normalized frames, offline decode of the whole sequence"),
        "frames_stream": w.add(f"{d}_frames_stream.npy", stream, TOL_FRAMES,
                               "decode case 0: normalized frames, PyTorch streaming step token by token"),
        "frames_denormalized": w.add(f"{d}_frames_denormalized.npy", denorm, tol_denorm,
                                     "decode case 0: frames_offline * std + mean"),
    }
    return [{"from_step_case": k, "n_tokens": int(len(seq)), "files": files}], {
        "decoder_stream_vs_offline": diffs["stream_vs_offline"], "decoder_onnx_vs_torch": diffs["onnx_vs_torch"]}


def write_rng_parity(w: ParityWriter, seed: int, n: int = 8) -> dict:
    a, b = SplitMix64([seed]), SplitMix64([seed])
    u64 = np.array([int(a.next_u64()[0]) for _ in range(n)], dtype=np.uint64)
    uni = np.array([float(b.next_uniform()[0]) for _ in range(n)], dtype=np.float64)
    return {"seed": int(seed), "files": {
        "u64": w.add("parity/rng/u64.npy", u64, 0.0, f"first {n} SplitMix64 next_u64 outputs, seed {seed}"),
        "uniform": w.add("parity/rng/uniform.npy", uni, 0.0,
                         f"first {n} uniforms (next_u64 >> 11) * 2^-53, seed {seed}")}}


def sampling_dict(params: SamplingParams, l_max: int) -> dict:
    """The sampling parameters as plain JSON numbers (max_len resolved against L_max)."""
    return {"temperature": float(params.temperature), "top_k": int(params.top_k),
            "min_len": int(params.min_len), "max_len": int(params.resolved_max_len(l_max)),
            "guidance": float(params.guidance)}


def write_parity(root: str | Path, *, gpt, vq, encoder, normalizer, step_path, decoder_path,
                 params: SamplingParams, seed: int, prompts: Sequence[str] = DEFAULT_STEP_PROMPTS,
                 n_logit_steps: int = 5) -> dict:
    """Write every parity file and parity/index.json; return the manifest's parity section.
    Works on CPU float32 eval copies (the caller's models are untouched)."""
    gpt = copy.deepcopy(gpt).cpu().float().eval()
    vq = copy.deepcopy(vq).cpu().float().eval()
    w = ParityWriter(root)
    text = index_text_parity(w)
    step, step_diff, codes = write_step_parity(w, gpt, encoder, step_path, params, seed, prompts, n_logit_steps)
    decode, dec_diff = write_decode_parity(w, vq, decoder_path, normalizer, codes)
    rng = write_rng_parity(w, seed)
    index = {"format": "comgrasp-parity", "version": 1, "files": w.files, "text": text,
             "step": step, "decode": decode, "rng": rng}
    (w.root / INDEX).write_text(json.dumps(index, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return {"index": INDEX, "tolerances": {"embedding": TOL_EMBEDDING, "text_states": TOL_STATES,
                                           "logits": TOL_LOGITS, "frames": TOL_FRAMES},
            "max_abs_diff": {**step_diff, **dec_diff}, "tokens_match": True}
