"""The Python side of the benchmark (DESIGN §7): the same prompt, seed and sequence length
as ``comgrasp bench``, through onnxruntime on the bundle's own ONNX files and through the
PyTorch reference with and without KV cache, timed per step and per decoded chunk;
``--table`` turns finished engine + Python runs into the report's Markdown tables
(``scripts/bench.sh`` runs all of it).

    python -m comgrasp_train.bench --bundle models/default --steps 74 --threads 1 --json

What runs (every backend draws its tokens with ``models.sampling``'s sampler, so equal
logits give equal tokens, and ``min_len = max_len = --steps`` fixes the length):

* ``onnxruntime``: the bundle's tokenizer.json through the ``tokenizers`` package exactly
  as the engine tokenizes (special tokens added, the file's fixed padding and truncation
  to ``max_tokens``: ``engine_tokenize``), text_encoder.onnx and the manifest's pooling,
  timed together as the engine times ``TextEncoder::embed``; ``OnnxStepRunner`` (the step
  graph with a numpy-owned fixed KV cache, exactly the engine's contract) and
  ``OnnxDecoderRunner`` on the tokens it sampled. ``--threads`` intra-op threads. Its time
  to first frame and real-time factor are derived from the component timings with the
  engine bench's formula (``derived_stream``).
* ``torch_kv``: ``ComGraspTransformer.decode_step`` with its fixed KV cache (what
  ``generate(use_cache=True)`` runs), the PyTorch text encoder, and the PyTorch streaming
  decoder per chunk. ``torch.set_num_threads(--threads)``.
* ``torch_nokv``: the full teacher-forced forward over the whole prefix at every step
  (``generate(use_cache=False)``); its per-step cost grows with the position, so the
  median and the mean over the sequence are both reported.

The PyTorch models come from, in this order: ``--torch-state FILE``; the bundle's own
native weights (``transformer.native`` / ``decoder.native``: one .npy per ``state_dict``
tensor, int8 ones dequantized, rebuilt with ``provenance.configs``); the random bundle's
``<bundle>/../<name>_torch.pt`` (``export.random_bundle``); the tiny bundle rebuilt from
its seed (``export.tiny``, deterministic); the training runs named in the provenance (with
the step/decoder weights int8-rounded as the exporter did when the bundle stores int8).
The PyTorch text encoder is rebuilt when it can be (the tiny one, all-MiniLM-L6-v2 from its
package); otherwise PyTorch runs on the onnxruntime embedding and its text time is n/a.
Without any weights the PyTorch columns say "PyTorch: n/a (no weights)"; nothing is
estimated.

Warm-up: ``--warmup`` steps (and one decode) per backend before the timed sequence.
Timings are wall clock (``time.perf_counter``), medians and p90 over the steps.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_PROMPT = "A woman drinks from the mug."


def stats(xs) -> dict | None:
    """median, p90 (nearest rank), mean, min, max, n: the Rust bench's definitions."""
    if not len(xs):
        return None
    s = np.sort(np.asarray(xs, dtype=np.float64))
    n = len(s)
    rank = lambda q: float(s[min(max(int(np.ceil(q * n)), 1), n) - 1])  # noqa: E731
    return {"median": float(np.median(s)), "p90": rank(0.9), "mean": float(s.mean()), "min": float(s[0]),
            "max": float(s[-1]), "n": n}


def tokens_sha256(tokens: np.ndarray) -> str:
    """SHA-256 of (steps, 4) tokens as little-endian int64, row-major (as the Rust bench)."""
    return hashlib.sha256(np.ascontiguousarray(np.asarray(tokens, dtype="<i8")).tobytes()).hexdigest()


def peak_rss_mib() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2**20


# ONNX data types of weights that a runtime holds as float32 (int8/uint8 ones are stored
# quantized and dequantized at load by Cast * Mul); int64/int32 initializers are shapes
# and indices, not weights.
_WEIGHT_DTYPES = {1, 2, 3, 10, 11, 16}  # FLOAT, UINT8, INT8, FLOAT16, DOUBLE, BFLOAT16


def onnx_weight_bytes(path: Path) -> tuple[int, int]:
    """(bytes of the graph's initializers as stored, inline or external; 4 bytes per element
    of every weight initializer: what tract and onnxruntime read per run once int8-stored
    weights are dequantized, the engine bench's ``fp32_bytes``), without loading external
    data."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    stored = fp32 = 0
    for t in model.graph.initializer:
        n = int(np.prod(t.dims)) if len(t.dims) else 1
        if t.data_type in _WEIGHT_DTYPES:
            fp32 += 4 * n
        ext = {e.key: e.value for e in t.external_data}
        if "length" in ext:
            stored += int(ext["length"])
        elif t.raw_data:
            stored += len(t.raw_data)
        else:
            stored += n * onnx.helper.tensor_dtype_to_np_dtype(t.data_type).itemsize
    return stored, fp32


# ----------------------------------------------------------------------------- helpers


class Bundle:
    """The parts of a bundle directory the Python benchmark needs."""

    def __init__(self, root: str | Path):
        from .models.gpt_configs import TransformerConfig

        self.root = Path(root)
        self.manifest = json.loads((self.root / "manifest.json").read_text(encoding="utf-8"))
        prov = self.manifest["provenance"]
        self.gpt_config = TransformerConfig.from_dict(prov["configs"]["transformer"])

    def path(self, rel: str) -> Path:
        return self.root / rel


def sampling(manifest: dict, steps: int, temperature: float | None, top_k: int | None):
    from .models.sampling import SamplingParams

    d = manifest["sampling"]
    return SamplingParams(temperature=d["temperature"] if temperature is None else temperature,
                          top_k=d["top_k"] if top_k is None else top_k, min_len=steps, max_len=steps,
                          guidance=d.get("guidance", 1.0))


class _WarmupDone(Exception):
    pass


def timed_loop(step_fn, cfg, params, seed: int, warmup: int, reset=None):
    """``run_sampling_loop`` with every step_fn call timed; ``warmup`` untimed steps first
    (then ``reset()``). Returns (tokens (steps, 4) int64, step times in ms)."""
    from .models.sampling import run_sampling_loop

    if warmup:
        def warm_fn(tokens, k):
            if k >= warmup:
                raise _WarmupDone
            return step_fn(tokens, k)

        try:
            run_sampling_loop(warm_fn, cfg, 1, params, [seed])
        except _WarmupDone:
            pass
        if reset is not None:
            reset()
    times: list[float] = []

    def timed(tokens, k):
        t = time.perf_counter()
        out = step_fn(tokens, k)
        times.append((time.perf_counter() - t) * 1e3)
        return out

    gen = run_sampling_loop(timed, cfg, 1, params, [seed])
    length = int(gen.lengths[0])
    # The forced End step (k = steps) is not a step the engine runs: drop its time.
    return gen.tokens[0, :length].numpy().astype(np.int64), times[:length]


# ----------------------------------------------------------------------------- onnxruntime


def engine_tokenize(tok, prompt: str, max_tokens: int) -> dict[str, np.ndarray]:
    """The engine's tokenization (src/text.rs ``TextEncoder::tokenize``): the bundle's
    tokenizer.json as is (its fixed right padding to ``max_tokens`` and its truncation),
    special tokens added, exactly ``max_tokens`` ids or an error. Returns (1, T) int64 feeds
    for every encoder input role, position ids included."""
    if not prompt.strip():
        raise ValueError("text is empty")
    e = tok.encode(prompt, add_special_tokens=True)
    if len(e.ids) != max_tokens:
        raise ValueError(f"tokenizer produced {len(e.ids)} tokens, the encoder takes exactly {max_tokens} "
                         "(tokenizer.json must pad to max_tokens, as the engine checks at load)")
    row = lambda v: np.asarray([v], dtype=np.int64)  # noqa: E731
    return {"input_ids": row(e.ids), "attention_mask": row(e.attention_mask), "token_type_ids": row(e.type_ids),
            "position_ids": np.arange(max_tokens, dtype=np.int64)[None]}


def ort_text_embedding(b: Bundle, prompt: str, threads: int, runs: int):
    """Tokenizer + text_encoder.onnx + pooling (the engine's path, in onnxruntime), timed
    as the engine times ``TextEncoder::embed``: tokenization included. Returns (embedding,
    times in ms, the input ids)."""
    import onnxruntime as ort
    import torch
    from tokenizers import Tokenizer

    from .text_encoder import pool_token_states

    te = b.manifest["text_encoder"]
    tok = Tokenizer.from_file(str(b.path(te["files"]["tokenizer"])))
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(b.path(te["files"]["onnx"])), opts, providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    wanted = [i["name"] for i in te["inputs"]]

    def embed():
        feeds = engine_tokenize(tok, prompt, te["max_tokens"])
        out = dict(zip(names, sess.run(None, {n: feeds[n] for n in wanted})))
        emb = pool_token_states(torch.from_numpy(out[te["pool_output"]]), torch.from_numpy(feeds["input_ids"]),
                                torch.from_numpy(feeds["attention_mask"]), pooling=te["pooling"],
                                normalize=te["normalize"], eos_id=te.get("eos_id"),
                                eos_selection=te.get("eos_selection")).numpy()
        return emb, feeds["input_ids"][0]

    emb, ids = embed()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        embed()
        times.append((time.perf_counter() - t) * 1e3)
    return emb, times, ids


def derived_stream(text_ms: float | None, first_step_ms: float | None, first_chunk_ms: float | None,
                   step_med: float | None, decode_med: float | None, frames_per_token: int, fps: float) -> dict:
    """Time to first frame and real-time factor from component timings, the same formula
    for every runtime: TTFF = text embedding + the condition step (pos 0, whose logits
    sample the first codes) + the first decoder chunk (the engine's generator emits its
    first frame right after that decode); RTF = frames per token / (median step + median
    chunk decode) / fps (steady state, sampling and assembly left out)."""
    parts = (text_ms, first_step_ms, first_chunk_ms)
    ttff = None if any(x is None for x in parts) else float(sum(parts))
    per_token = None if step_med is None or decode_med is None else step_med + decode_med
    rtf = None if not per_token else frames_per_token * 1e3 / per_token / fps
    return {"ttff_ms": ttff, "ms_per_token": per_token, "rtf": rtf}


def bench_onnxruntime(b: Bundle, prompt: str, params, seed: int, threads: int, warmup: int,
                      text_runs: int) -> tuple[dict, np.ndarray]:
    """(the onnxruntime report, the text embedding it computed)."""
    import onnxruntime as ort

    from .export.decoder_graph import OnnxDecoderRunner
    from .export.step_graph import OnnxStepRunner

    cfg = b.gpt_config
    emb, text_ms, ids = ort_text_embedding(b, prompt, threads, text_runs)
    t = time.perf_counter()
    runner = OnnxStepRunner(b.path(b.manifest["transformer"]["file"]), cfg, emb, threads=threads)
    load_ms = (time.perf_counter() - t) * 1e3

    def reset():
        for c in runner.cache.values():
            c.fill(0.0)

    tokens, step_ms = timed_loop(runner.step_fn, cfg, params, seed, warmup, reset)
    dec = b.manifest["decoder"]
    t = time.perf_counter()
    drun = OnnxDecoderRunner(b.path(dec["file"]), dec["initial_state"], threads=threads)
    load_ms += (time.perf_counter() - t) * 1e3
    drun.step(tokens[:1])  # warm-up
    drun.reset()
    decode_ms = []
    for row in tokens:
        t = time.perf_counter()
        drun.step(row[None])
        decode_ms.append((time.perf_counter() - t) * 1e3)
    text_s, step_s, decode_s = stats(text_ms), stats(step_ms), stats(decode_ms)
    stream = derived_stream(text_s["median"], step_ms[0], decode_ms[0], step_s["median"], decode_s["median"],
                            b.manifest["frames_per_token"], b.manifest["fps"])
    return {"version": ort.__version__, "session_load_ms": load_ms, "text_ms": text_s,
            "text_input_ids": ids.tolist(), "step_ms": step_s, "first_step_ms": step_ms[0],
            "decode_ms": decode_s, "first_decode_ms": decode_ms[0], "stream": stream,
            "tokens": tokens.tolist(), "tokens_sha256": tokens_sha256(tokens)}, emb


# ----------------------------------------------------------------------------- PyTorch



def _native_ok(section) -> bool:
    return isinstance(section, dict) and bool(section.get("tensors")) and "dir" in section


def torch_from_native(b: Bundle):
    """(gpt, vq, text encoder or None, source) rebuilt from the bundle's own native weights
    (``export.bundle.torch_models_from_native``: one .npy per PyTorch ``state_dict`` tensor,
    int8 ones dequantized to exactly the values the graphs compute with) and the model
    configs in ``provenance.configs``. Raises ValueError when the sections do not cover what
    generation and decoding need."""
    from .export.bundle import bundle_text_encoder, torch_models_from_native

    gpt, vq = torch_models_from_native(b.root, b.manifest)
    return gpt, vq, bundle_text_encoder(b.manifest, root=b.root), "the bundle's native weights"


def _tiny_seed(cmds: str) -> int:
    from .export.bundle import tiny_seed_of

    return tiny_seed_of(cmds)


def load_torch_models(b: Bundle, torch_state: str | None):
    """(gpt, vq, text encoder or None, source description), or (None, why) (see the module
    doc). A None text encoder means PyTorch runs on the onnxruntime text embedding."""
    from .export.random_bundle import load_torch_state, torch_state_path

    m = b.manifest
    prov = m["provenance"]
    if torch_state:
        gpt, vq, enc = load_torch_state(torch_state)
        return gpt, vq, enc, f"state dicts {torch_state}"
    notes = []
    if _native_ok(m["transformer"].get("native")) and _native_ok(m["decoder"].get("native")):
        try:
            return torch_from_native(b)
        except (ValueError, KeyError, OSError, RuntimeError) as e:
            notes.append(f"native weights unusable: {e}")
    path = torch_state_path(b.root)
    if path.is_file():
        gpt, vq, enc = load_torch_state(path)
        return gpt, vq, enc, f"state dicts {path}"
    cmds = " ".join(prov.get("commands") or [])
    if "comgrasp_train.export.tiny" in cmds:
        from .export.tiny import tiny_gpt, tiny_text_encoder, tiny_vq

        seed = _tiny_seed(cmds)
        return tiny_gpt(seed)[0], tiny_vq(seed)[0], tiny_text_encoder(seed), f"tiny bundle rebuilt from seed {seed}"
    runs = prov.get("runs") or {}
    if runs.get("vq") and runs.get("gpt") and Path(runs["vq"]).is_dir() and Path(runs["gpt"]).is_dir():
        from .inference import MotionModel

        mm = MotionModel.load(Path(runs["vq"]), Path(runs["gpt"]), "cpu")
        source = f"training runs {runs['vq']}, {runs['gpt']}"
        graph_w = prov.get("graph_weights") or {}
        if graph_w:
            # The bundle was exported with int8 weights: round the same tensors as the
            # exporter (export_trained_bundle), so PyTorch computes what the graphs compute.
            from .export.bundle import DECODER_FILE, STEP_FILE
            from .weight_quant import fake_quantize_int8

            with __import__("torch").no_grad():
                if STEP_FILE in graph_w:
                    fake_quantize_int8(mm.gpt)
                if DECODER_FILE in graph_w:
                    for part in mm.vq.parts.values():
                        fake_quantize_int8(part.decoder)
            source += " (step/decoder weights int8-rounded as exported)"
        return mm.gpt, mm.vq, mm.encoder, source
    notes.append("no weights")
    return None, "; ".join(notes)


def bench_torch(models, prompt: str, params, seed: int, threads: int, warmup: int, text_runs: int,
                no_cache: bool, ort_emb: np.ndarray, frames_per_token: int, fps: float) -> dict:
    import torch

    from .models.streaming import StreamingDecoder

    gpt, vq, enc, source = models
    gpt, vq = gpt.float().eval(), vq.float().eval()
    cfg = gpt.cfg
    out: dict = {"version": torch.__version__, "source": source, "threads": torch.get_num_threads()}
    if enc is not None:
        enc.clear_cache()
        emb = enc.encode_uncached([prompt]).to(torch.float32)
        text_ms = []
        for _ in range(text_runs):
            t = time.perf_counter()
            enc.encode_uncached([prompt])
            text_ms.append((time.perf_counter() - t) * 1e3)
        out["text_ms"] = stats(text_ms)
    else:
        emb = torch.from_numpy(np.asarray(ort_emb, dtype=np.float32).reshape(1, -1))
        out["text_ms"] = None
        out["text_note"] = "no PyTorch text encoder for this bundle: the onnxruntime embedding is used"

    with torch.no_grad():
        cache = {"c": gpt.new_cache(1)}

        def kv_step(tokens, k):
            lg = gpt.decode_step(torch.from_numpy(tokens), k, emb, cache["c"])
            return [x.float().numpy() for x in lg]

        def reset():
            cache["c"] = gpt.new_cache(1)

        tokens, step_ms = timed_loop(kv_step, cfg, params, seed, warmup, reset)
        out["kv"] = {"step_ms": stats(step_ms), "tokens": tokens.tolist(), "tokens_sha256": tokens_sha256(tokens)}

        sd = StreamingDecoder(vq, batch_size=1)
        sd.step(torch.from_numpy(tokens[:1]))  # warm-up
        sd.reset(1)
        decode_ms = []
        for row in tokens:
            t = time.perf_counter()
            sd.step(torch.from_numpy(row[None]))
            decode_ms.append((time.perf_counter() - t) * 1e3)
        out["decode_ms"] = stats(decode_ms)
        out["stream"] = derived_stream(_med(out, "text_ms", "median"), step_ms[0], decode_ms[0],
                                       out["kv"]["step_ms"]["median"], out["decode_ms"]["median"],
                                       frames_per_token, fps)

        if no_cache:
            prefix: list = []

            def full_step(tokens, k):
                t = torch.from_numpy(tokens)
                if k > 0:
                    prefix.append(t)
                seq = torch.stack(prefix, 1) if prefix else t.new_zeros((1, 0, t.shape[1]))
                return [lg[:, -1].float().numpy() for lg in gpt(emb, seq)]

            tokens_nc, nc_ms = timed_loop(full_step, cfg, params, seed, warmup, prefix.clear)
            out["nokv"] = {"step_ms": stats(nc_ms), "total_ms": float(np.sum(nc_ms)), "tokens": tokens_nc.tolist(),
                           "tokens_sha256": tokens_sha256(tokens_nc)}
    return out


# ----------------------------------------------------------------------------- the table


def _f(x, nd=2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{nd}f}"


def _ratio(a, b) -> str:
    if a is None or b is None or not b:
        return "n/a"
    r = a / b
    return f"{r:.2f}" if r >= 0.1 else f"{r:.3f}" if r >= 0.001 else f"{r:.1e}"


def _med(d, *path):
    for p in path:
        if d is None:
            return None
        d = d.get(p)
    return d


def _pair(a, b, nd=2) -> str:
    return f"{_f(a, nd)} / {_f(b, nd)}"


def _bw_at(bw: dict, threads: int):
    """The read bandwidth (GB/s) measured at the run's thread count (1 or >= 2)."""
    return bw.get("gb_per_s_1t") if threads <= 1 else bw.get("gb_per_s_run", bw.get("gb_per_s_2t"))


def _engine_path(e: dict) -> str:
    p = e.get("engine_path") or {}
    step, dec = p.get("step", "tract"), p.get("decoder", "tract")
    return step if step == dec else f"step {step}, decoder {dec}"


def limit_row(e: dict, ort_step: float | None) -> dict:
    """The bandwidth limit of a token step at the run's thread count: bytes one step must
    read ÷ the measured read bandwidth, for the fp32 weights (what tract and onnxruntime
    read, int8-stored weights included: they are dequantized at load) and, when the bundle
    has native int8 weights, for those (what the native path reads); + the fp32 KV cache.
    The engine's ratio uses the byte count of the path it ran."""
    w = (e.get("model") or {}).get("weights") or {}
    kv = (e.get("model") or {}).get("kv_cache_bytes") or 0
    fp32 = w.get("fp32_bytes", (e.get("model") or {}).get("step_graph_bytes"))
    # What the native step says it reads per step when it ran (gathered embedding rows and
    # the pos-0-only text projection left out), else the whole native section.
    int8 = w.get("native_step_reported_bytes") or w.get("int8_bytes")
    gbps = _bw_at(e.get("bandwidth") or {}, int(e["threads"]["tract"]))
    lim = lambda n: None if n is None or not gbps else (n + kv) / (gbps * 1e9) * 1e3  # noqa: E731
    step_path = (e.get("engine_path") or {}).get("step", "tract")
    use_int8 = step_path == "native" and int8 is not None
    eng = _med(e, "step_ms", "median")
    own = lim(int8) if use_int8 else lim(fp32)
    mb = lambda n: None if n is None else n / 1e6  # noqa: E731
    return {"gbps": gbps, "fp32_mb": mb(fp32), "int8_mb": mb(int8),
            "kv_mb": kv / 1e6, "lim_fp32": lim(fp32), "lim_int8": lim(int8), "engine": eng,
            "engine_over": None if eng is None or not own else eng / own, "basis": "int8" if use_int8 else "fp32",
            "ort_over": None if ort_step is None or not lim(fp32) else ort_step / lim(fp32)}


def _separator(header: str) -> str:
    """The Markdown separator row for a table's header row (one cell per column)."""
    return "|" + "---|" * (header.count("|") - 1)


def markdown_table(runs: list[tuple[str, dict, dict]]) -> str:
    """Markdown tables from (bundle name, engine JSON, python JSON) triples, one row per
    triple (a bundle x engine path x thread count). Ratios are engine time / other time
    (< 1: the engine is faster); for the real-time factor, a speed, other RTF / engine RTF
    (the same time ratio)."""
    out = []
    ort_rows, bw_rows, torch_rows, stream_rows, agree_rows = [], [], [], [], []
    for name, e, p in runs:
        path = _engine_path(e)
        th = e["threads"]["tract"]
        th_s = str(th) if th == p["threads"] else f"{th} / {p['threads']}"
        key = f"| {name} | {path} | {th_s} |"
        o = p.get("onnxruntime") or {}
        ed, od = e.get("derived") or {}, o.get("stream") or {}
        et, ot = _med(e, "text_ms", "median"), _med(o, "text_ms", "median")
        es, os_ = _med(e, "step_ms", "median"), _med(o, "step_ms", "median")
        ec, oc = _med(e, "decode_ms", "median"), _med(o, "decode_ms", "median")
        ef, of = ed.get("ttff_ms"), od.get("ttff_ms")
        er, orr = ed.get("rtf"), od.get("rtf")
        ort_rows.append(f"{key} {_pair(et, ot)} | {_pair(es, os_, 3)} | {_pair(ec, oc, 3)} | {_pair(ef, of)} | "
                        f"{_pair(er, orr, 1)} | {_ratio(et, ot)} | {_ratio(es, os_)} | {_ratio(ec, oc)} | "
                        f"{_ratio(ef, of)} | {_ratio(orr, er)} |")
        lr = limit_row(e, os_)
        bw_rows.append(f"{key} {_f(lr['gbps'], 1)} | {_f(lr['fp32_mb'], 1)} | "
                       f"{'—' if lr['int8_mb'] is None else _f(lr['int8_mb'], 1)} | {_f(lr['kv_mb'], 1)} | "
                       f"{_f(lr['lim_fp32'], 3)} | {'—' if lr['lim_int8'] is None else _f(lr['lim_int8'], 3)} | "
                       f"{_f(lr['engine'], 3)} | {_f(lr['engine_over'])} ({lr['basis']}) | {_f(lr['ort_over'])} |")
        t = p.get("torch")
        if t:
            tkv, tno = _med(t, "kv", "step_ms", "median"), _med(t, "nokv", "step_ms", "mean")
            tt, tc = _med(t, "text_ms", "median"), _med(t, "decode_ms", "median")
            ts = t.get("stream") or {}
            torch_rows.append(f"{key} {t['source']} | {_f(tt)} | {_f(tkv, 3)} | {_f(tno, 3)} | {_f(tc, 3)} | "
                              f"{_f(ts.get('ttff_ms'))} | {_f(ts.get('rtf'), 1)} | {_ratio(es, tkv)} | "
                              f"{_ratio(es, tno)} | {_ratio(ec, tc)} | {_ratio(ts.get('rtf'), er)} |")
        else:
            why = p.get("torch_note") or "no weights"
            torch_rows.append(f"{key} PyTorch: n/a ({why}) |" + " n/a |" * 10)
        st = e["stream"]
        stream_rows.append(
            f"{key} {_f(_med(st, 'ttff_ms', 'median'))} | {_f(_med(st, 'ms_per_token', 'median'), 3)} | "
            f"{_f(_med(st, 'frames_per_s', 'median'), 0)} | {_f(_med(st, 'rtf', 'median'), 1)} | "
            f"{_f(e.get('load_ms'), 0)} | {_f(_med(e, 'poll_ns', 'empty', 'median'), 1)} | "
            f"{_f(_med(e, 'poll_ns', 'ready', 'median'), 1)} | {_f(_med(e, 'rss_mib', 'peak'), 0)} | "
            f"{_f(p.get('peak_rss_mib'), 0)} | {_f(_med(e, 'minor_page_faults_per_token', 'stream'), 0)} |")
        hashes = {"onnxruntime": o.get("tokens_sha256"), "torch KV": _med(t, "kv", "tokens_sha256"),
                  "torch no KV": _med(t, "nokv", "tokens_sha256")}
        same = {k: ("n/a" if v is None else ("yes" if v == e["tokens_sha256"] else "**NO**"))
                for k, v in hashes.items()}
        eids, oids = e.get("text_input_ids"), o.get("text_input_ids")
        text_same = "n/a" if eids is None or oids is None else ("yes" if list(eids) == list(oids) else "**NO**")
        agree_rows.append(f"{key} {e['config']['steps']} | {e['tokens_sha256'][:12]} | {same['onnxruntime']} | "
                          f"{same['torch KV']} | {same['torch no KV']} | "
                          f"{'yes' if st.get('matches_step_loop') else '**NO**'} | {text_same} |")
    out.append("**Engine vs onnxruntime** (the same ONNX files, inputs and thread count; ms, medians; cells are "
               "engine / ORT). TTFF = text embedding + condition step (pos 0) + first decoder chunk; RTF = "
               "frames per token / (step + chunk) / fps; both from component timings, the same formula for both "
               "runtimes (the engine's measured end-to-end stream is further down). Ratios = engine time / ORT "
               "time (< 1: engine faster).\n")
    out.append("| bundle | engine path | threads | text ms | step ms | chunk ms | TTFF ms | RTF | engine/ORT text | "
               "step | chunk | TTFF | RTF |")
    out.append(_separator(out[-1]))
    out += ort_rows
    out.append("\n**Bandwidth limit of a token step** = (weight bytes read per step + the fp32 KV cache) ÷ the read "
               "bandwidth measured in the same run at the run's thread count. fp32 = every step-graph weight as "
               "tract and onnxruntime hold it in memory (int8-stored weights are dequantized to fp32 at load); "
               "int8 = the native path's bytes (int8 weights + scales + its fp32 tensors; on native rows what "
               "the native step reports it reads per step, on tract rows the whole `transformer.native` "
               "section; — without one). The engine's ratio uses the byte count of the path it ran; ORT "
               "reads fp32. Weights smaller than the L3 stay cached from one step to the next, so there the "
               "limit is no floor (ratios < 1 are possible); it binds once the weights exceed the L3.\n")
    out.append("| bundle | engine path | threads | read GB/s | fp32 weights MB/step | int8 weights MB/step | "
               "KV cache MB | limit ms (fp32) | limit ms (int8) | engine step ms | engine/limit | ORT/limit (fp32) |")
    out.append(_separator(out[-1]))
    out += bw_rows
    out.append("\n**PyTorch reference** (same tokens; KV = `decode_step` with its fixed cache, no KV = the full "
               "forward over the prefix at every step, mean over the sequence). Ratios = engine time / PyTorch "
               "time.\n")
    out.append("| bundle | engine path | threads | weights | text ms | KV step ms | no-KV step ms | chunk ms | "
               "TTFF ms | RTF | engine/torch KV | engine/torch no KV | engine/torch chunk | engine/torch RTF |")
    out.append(_separator(out[-1]))
    out += torch_rows
    out.append("\n**The engine end to end** (`Engine::start` .. last frame on the loaded bundle; TTFF = start to "
               "first frame in the consumer's hands; RTF = frames/s ÷ fps over the whole generation, text "
               "included), load time, `Stream::poll` ns (empty ring / ready frame), peak RSS MiB (engine / "
               "python process) and minor page faults per token.\n")
    out.append("| bundle | engine path | threads | TTFF ms | ms/token | frames/s | RTF | load ms | poll empty ns | "
               "poll ready ns | engine RSS | python RSS | faults/token |")
    out.append(_separator(out[-1]))
    out += stream_rows
    out.append("\n**Same tokens** (SHA-256 of the (steps, 4) int64 tokens, compared with the engine's; its stream "
               "frames are compared with its step loop's tokens decoded and assembled; text ids = the "
               "tokenizer's ids for the prompt, engine vs the `tokenizers` package on the bundle's "
               "tokenizer.json).\n")
    out.append("| bundle | engine path | threads | steps | engine tokens | = onnxruntime | = torch KV | "
               "= torch no KV | stream = step loop | text ids = |")
    out.append(_separator(out[-1]))
    out += agree_rows
    return "\n".join(out)


# ----------------------------------------------------------------------------- main


def run(bundle: str | Path, *, prompt: str = DEFAULT_PROMPT, seed: int | None = None, steps: int | None = None,
        threads: int = 1, warmup: int = 3, temperature: float | None = None, top_k: int | None = None,
        text_runs: int = 10, torch_state: str | None = None, use_torch: bool = True, no_cache: bool = True) -> dict:
    import torch

    torch.set_num_threads(threads)
    b = Bundle(bundle)
    m = b.manifest
    steps = m["l_max"] if steps is None else steps
    seed = m["sampling"]["seed"] if seed is None else seed
    params = sampling(m, steps, temperature, top_k)
    stored, fp32 = onnx_weight_bytes(b.path(m["transformer"]["file"]))
    report: dict = {
        "runtime": "python", "bundle": str(bundle), "threads": threads,
        "config": {"prompt": prompt, "seed": seed, "steps": steps, "warmup": warmup,
                   "temperature": params.temperature, "top_k": params.top_k, "fps": m["fps"]},
        "model": {"step_weight_bytes": stored, "step_fp32_weight_bytes": fp32,
                  "step_graph_bytes": sum(e["bytes"] for p, e in m["files"].items()
                                          if p.startswith(m["transformer"]["file"]))},
    }
    report["onnxruntime"], ort_emb = bench_onnxruntime(b, prompt, params, seed, threads, warmup, text_runs)
    loaded = load_torch_models(b, torch_state) if use_torch else (None, "skipped (--no-torch)")
    if loaded[0] is not None:
        report["torch"] = bench_torch(loaded, prompt, params, seed, threads, warmup, text_runs, no_cache, ort_emb,
                                      m["frames_per_token"], m["fps"])
    else:
        report["torch"] = None
        report["torch_note"] = loaded[1]
    del loaded
    report["peak_rss_mib"] = peak_rss_mib()
    return report


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", help="bundle directory (required unless --table)")
    ap.add_argument("--table", nargs="+", metavar="NAME=ENGINE.json,PYTHON.json", default=None,
                    help="print the Markdown comparison of finished runs instead of benchmarking")
    ap.add_argument("--prompt", default=DEFAULT_PROMPT)
    ap.add_argument("--seed", type=int, default=None, help="sampler seed (default: the bundle's)")
    ap.add_argument("--steps", type=int, default=None, help="token steps (default: L_max)")
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op and torch threads")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--temperature", type=float, default=None)
    ap.add_argument("--top-k", type=int, default=None)
    ap.add_argument("--text-runs", type=int, default=10)
    ap.add_argument("--torch-state", default=None, help="PyTorch weights (default: <bundle>/../<name>_torch.pt)")
    ap.add_argument("--no-torch", action="store_true", help="onnxruntime only")
    ap.add_argument("--no-nokv", action="store_true", help="skip the PyTorch run without KV cache")
    ap.add_argument("--json", action="store_true", help="print JSON (default: a short summary)")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    a = ap.parse_args(argv)
    if a.table:
        runs = []
        for spec in a.table:
            name, _, files = spec.partition("=")
            eng, _, py = files.partition(",")
            runs.append((name, json.loads(Path(eng).read_text()), json.loads(Path(py).read_text())))
        print(markdown_table(runs))
        return
    if not a.bundle:
        ap.error("--bundle is required")
    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    r = run(a.bundle, prompt=a.prompt, seed=a.seed, steps=a.steps, threads=a.threads, warmup=a.warmup,
            temperature=a.temperature, top_k=a.top_k, text_runs=a.text_runs, torch_state=a.torch_state,
            use_torch=not a.no_torch, no_cache=not a.no_nokv)
    text = json.dumps(r, indent=1)
    if a.out:
        Path(a.out).write_text(text + "\n", encoding="utf-8")
    if a.json:
        print(text)
        return
    o, t = r["onnxruntime"], r["torch"]
    print(f"{a.bundle}: {r['config']['steps']} steps, {a.threads} thread(s)")
    print(f"  onnxruntime {o['version']}: step {o['step_ms']['median']:.3f} ms, "
          f"decode {o['decode_ms']['median']:.3f} ms, "
          f"text {o['text_ms']['median']:.2f} ms; tokens {o['tokens_sha256'][:16]}")
    if t:
        print(f"  torch {t['version']} ({t['source']}): KV step {t['kv']['step_ms']['median']:.3f} ms, "
              f"decode {t['decode_ms']['median']:.3f} ms; tokens {t['kv']['tokens_sha256'][:16]}")
        if "nokv" in t:
            print(f"  torch without cache: step median {t['nokv']['step_ms']['median']:.3f} ms, "
                  f"mean {t['nokv']['step_ms']['mean']:.3f} ms; tokens {t['nokv']['tokens_sha256'][:16]}")
    else:
        print(f"  torch: {r['torch_note']}")


if __name__ == "__main__":
    main()
