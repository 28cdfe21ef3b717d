"""The Python side of the benchmark (DESIGN §7): the same prompt, seed and sequence length
as ``comgrasp bench``, through onnxruntime on the bundle's own ONNX files and through the
PyTorch reference with and without KV cache, timed per step and per decoded chunk.

    python -m comgrasp_train.bench --bundle out/bench/paper --steps 74 --threads 1 --json

What runs (every backend draws its tokens with ``models.sampling``'s sampler, so equal
logits give equal tokens, and ``min_len = max_len = --steps`` fixes the length):

* ``onnxruntime``: the text encoder graph + pooling in Python, ``OnnxStepRunner`` (the
  step graph with a numpy-owned fixed KV cache, exactly the engine's contract) and
  ``OnnxDecoderRunner`` on the tokens it sampled. ``--threads`` intra-op threads.
* ``torch_kv``: ``ComGraspTransformer.decode_step`` with its fixed KV cache (what
  ``generate(use_cache=True)`` runs), the PyTorch text encoder, and the PyTorch streaming
  decoder per chunk. ``torch.set_num_threads(--threads)``.
* ``torch_nokv``: the full teacher-forced forward over the whole prefix at every step
  (``generate(use_cache=False)``); its per-step cost grows with the position, so the
  median and the mean over the sequence are both reported.

The PyTorch models come from, in this order: ``--torch-state FILE``; the random bundle's
``<bundle>/../<name>_torch.pt`` (``export.random_bundle``); the tiny bundle rebuilt from
its seed (``export.tiny``, deterministic); the training runs named in the provenance.
Without any, the PyTorch columns are skipped (reported as such).

Warm-up: ``--warmup`` steps (and one decode) per backend before the timed sequence.
Timings are wall clock (``time.perf_counter``), medians and p90 over the steps.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
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


def onnx_weight_bytes(path: Path) -> int:
    """Bytes of the graph's initializers (inline or external), without loading external data."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    total = 0
    for t in model.graph.initializer:
        ext = {e.key: e.value for e in t.external_data}
        if "length" in ext:
            total += int(ext["length"])
        elif t.raw_data:
            total += len(t.raw_data)
        else:
            n = int(np.prod(t.dims)) if len(t.dims) else 1
            total += n * onnx.helper.tensor_dtype_to_np_dtype(t.data_type).itemsize
    return total


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
                          top_k=d["top_k"] if top_k is None else top_k, min_len=steps, max_len=steps)


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


def ort_text_embedding(b: Bundle, prompt: str, threads: int, runs: int):
    """Tokenizer + text_encoder.onnx + pooling (the engine's path, in onnxruntime)."""
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

    def embed():
        e = tok.encode(prompt)
        t = te["max_tokens"]
        feeds = {"input_ids": np.array([e.ids], np.int64), "attention_mask": np.array([e.attention_mask], np.int64),
                 "token_type_ids": np.array([e.type_ids], np.int64),
                 "position_ids": np.arange(t, dtype=np.int64)[None]}
        out = dict(zip(names, sess.run(None, {i["name"]: feeds[i["name"]] for i in te["inputs"]})))
        return pool_token_states(torch.from_numpy(out[te["pool_output"]]), torch.from_numpy(feeds["input_ids"]),
                                 torch.from_numpy(feeds["attention_mask"]), pooling=te["pooling"],
                                 normalize=te["normalize"], eos_id=te.get("eos_id"),
                                 eos_selection=te.get("eos_selection")).numpy()

    emb = embed()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        embed()
        times.append((time.perf_counter() - t) * 1e3)
    return emb, times


def bench_onnxruntime(b: Bundle, prompt: str, params, seed: int, threads: int, warmup: int, text_runs: int) -> dict:
    import onnxruntime as ort

    from .export.decoder_graph import OnnxDecoderRunner
    from .export.step_graph import OnnxStepRunner

    cfg = b.gpt_config
    emb, text_ms = ort_text_embedding(b, prompt, threads, text_runs)
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
    return {"version": ort.__version__, "session_load_ms": load_ms, "text_ms": stats(text_ms),
            "step_ms": stats(step_ms), "decode_ms": stats(decode_ms), "tokens": tokens.tolist(),
            "tokens_sha256": tokens_sha256(tokens)}


# ----------------------------------------------------------------------------- PyTorch


def load_torch_models(b: Bundle, torch_state: str | None):
    """(gpt, vq, text encoder, source description) or None (see the module doc)."""
    from .export.random_bundle import load_torch_state, torch_state_path

    prov = b.manifest["provenance"]
    path = Path(torch_state) if torch_state else torch_state_path(b.root)
    if path.is_file():
        gpt, vq, enc = load_torch_state(path)
        return gpt, vq, enc, f"state dicts {path}"
    cmds = " ".join(prov.get("commands") or [])
    if "comgrasp_train.export.tiny" in cmds:
        from .export.tiny import tiny_gpt, tiny_text_encoder, tiny_vq

        m = re.search(r"--seed (\d+)", cmds)
        seed = int(m.group(1)) if m else 0
        return tiny_gpt(seed)[0], tiny_vq(seed)[0], tiny_text_encoder(seed), f"tiny bundle rebuilt from seed {seed}"
    runs = prov.get("runs") or {}
    if runs.get("vq") and runs.get("gpt") and Path(runs["vq"]).is_dir() and Path(runs["gpt"]).is_dir():
        from .inference import MotionModel

        mm = MotionModel.load(Path(runs["vq"]), Path(runs["gpt"]), "cpu")
        return mm.gpt, mm.vq, mm.encoder, f"training runs {runs['vq']}, {runs['gpt']}"
    return None


def bench_torch(models, prompt: str, params, seed: int, threads: int, warmup: int, text_runs: int,
                no_cache: bool) -> dict:
    import torch

    from .models.streaming import StreamingDecoder

    gpt, vq, enc, source = models
    gpt, vq = gpt.float().eval(), vq.float().eval()
    cfg = gpt.cfg
    enc.clear_cache()
    emb = enc.encode_uncached([prompt]).to(torch.float32)
    text_ms = []
    for _ in range(text_runs):
        t = time.perf_counter()
        enc.encode_uncached([prompt])
        text_ms.append((time.perf_counter() - t) * 1e3)
    out: dict = {"version": torch.__version__, "source": source, "threads": torch.get_num_threads(),
                 "text_ms": stats(text_ms)}

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
    return "n/a" if a is None or b is None or not b else f"{a / b:.2f}"


def _med(d, *path):
    for p in path:
        if d is None:
            return None
        d = d.get(p)
    return d


def markdown_table(runs: list[tuple[str, dict, dict]]) -> str:
    """Markdown tables from (name, engine JSON, python JSON) triples. Ratios are
    engine time / other time (< 1: the engine is faster)."""
    out = []
    step_rows, stream_rows, sys_rows, agree_rows = [], [], [], []
    for name, e, p in runs:
        th = f"{e['threads']['tract']} / {p['threads']}"
        eng = _med(e, "step_ms", "median")
        ort = _med(p, "onnxruntime", "step_ms", "median")
        tkv = _med(p, "torch", "kv", "step_ms", "median")
        tno = _med(p, "torch", "nokv", "step_ms", "mean")
        bw = e.get("bandwidth") or {}
        lim1, lim2 = bw.get("step_limit_ms_1t"), bw.get("step_limit_ms_2t")
        mb = e["model"]["step_graph_bytes"] / 1e6
        step_rows.append(f"| {name} | {th} | {mb:.1f} | {_f(eng, 3)} | {_f(ort, 3)} | {_f(tkv, 3)} | {_f(tno, 3)} | "
                         f"{_ratio(eng, ort)} | {_ratio(eng, tkv)} | {_ratio(eng, tno)} | "
                         f"{_f(lim1, 2)} / {_f(lim2, 2)} | "
                         f"{_ratio(eng, lim1)} / {_ratio(eng, lim2)} |")
        ec = _med(e, "decode_ms", "median")
        oc = _med(p, "onnxruntime", "decode_ms", "median")
        tc = _med(p, "torch", "decode_ms", "median")
        s = e["stream"]
        stream_rows.append(
            f"| {name} | {th} | {_f(ec, 3)} | {_f(oc, 3)} | {_f(tc, 3)} | {_ratio(ec, oc)} | "
            f"{_f(_med(e, 'text_ms', 'median'), 2)} / {_f(_med(p, 'onnxruntime', 'text_ms', 'median'), 2)} / "
            f"{_f(_med(p, 'torch', 'text_ms', 'median'), 2)} | {_f(s['ttff_ms']['median'], 2)} | "
            f"{_f(s['ms_per_token']['median'], 3)} | {_f(s['frames_per_s']['median'], 0)} | "
            f"{_f(s['rtf']['median'], 1)} | "
            f"{_f(e['load_ms'], 0)} |")
        sys_rows.append(
            f"| {name} | {_f(_med(e, 'poll_ns', 'empty', 'median'), 1)} | "
            f"{_f(_med(e, 'poll_ns', 'ready', 'median'), 1)} | "
            f"{_f(_med(e, 'rss_mib', 'peak'), 0)} | {_f(p.get('peak_rss_mib'), 0)} | "
            f"{_f(bw.get('gb_per_s_1t'), 1)} / {_f(bw.get('gb_per_s_2t'), 1)} | "
            f"{_f(_med(e, 'minor_page_faults_per_token', 'stream'), 0)} / "
            f"{_f(_med(e, 'minor_page_faults_per_token', 'step_loop'), 0)} |")
        hashes = {"engine": e["tokens_sha256"], "onnxruntime": _med(p, "onnxruntime", "tokens_sha256"),
                  "torch KV": _med(p, "torch", "kv", "tokens_sha256"),
                  "torch no KV": _med(p, "torch", "nokv", "tokens_sha256")}
        same = {k: ("n/a" if v is None else ("yes" if v == hashes["engine"] else "**NO**")) for k, v in hashes.items()}
        agree_rows.append(f"| {name} | {e['config']['steps']} | {e['tokens_sha256'][:12]} | {same['onnxruntime']} | "
                          f"{same['torch KV']} | {same['torch no KV']} | "
                          f"{'yes' if e['stream'].get('matches_step_loop') else '**NO**'} |")
    out.append("Token step (ms, median; torch without cache: mean over the sequence). Ratios = engine / other "
               "(< 1: engine faster). Bandwidth limit = (step graph weights + KV cache) / measured read bandwidth, "
               "1 thread / 2 threads.\n")
    out.append("| bundle | threads engine / python | step graph MB | engine | onnxruntime | torch KV | torch no KV | "
               "engine/ORT | engine/torch KV | engine/torch no KV | BW limit ms | engine/BW limit |")
    out.append("|" + "---|" * 12)
    out += step_rows
    out.append("\nDecoder chunk (16 frames, ms, median), text embedding (ms: engine / ORT / torch) and the "
               "end-to-end stream of the engine (TTFF = start to first frame in the consumer's hands; "
               "RTF = frames/s / fps).\n")
    out.append("| bundle | threads | engine ms/chunk | ORT ms/chunk | torch ms/chunk | engine/ORT | text ms | "
               "TTFF ms | stream ms/token | frames/s | RTF | load ms |")
    out.append("|" + "---|" * 12)
    out += stream_rows
    out.append("\nPoll latency (ns per `Stream::poll`, median over batches of 64 calls), peak RSS (MiB), "
               "memory read bandwidth (GB/s, 1 / 2 threads) and minor page faults per token (stream worker / "
               "the same work in the bench's own loop).\n")
    out.append("| bundle | poll empty ns | poll ready ns | engine peak RSS | python peak RSS | read GB/s | "
               "page faults/token |")
    out.append("|" + "---|" * 7)
    out += sys_rows
    out.append("\nSame tokens (SHA-256 of the (steps, 4) int64 tokens; the engine's stream frames are compared "
               "with its step loop's tokens decoded and assembled).\n")
    out.append("| bundle | steps | engine tokens | = onnxruntime | = torch KV | = torch no KV | stream = step loop |")
    out.append("|" + "---|" * 7)
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
    step_file = b.path(m["transformer"]["file"])
    report: dict = {
        "runtime": "python", "bundle": str(bundle), "threads": threads,
        "config": {"prompt": prompt, "seed": seed, "steps": steps, "warmup": warmup,
                   "temperature": params.temperature, "top_k": params.top_k, "fps": m["fps"]},
        "model": {"step_weight_bytes": onnx_weight_bytes(step_file),
                  "step_graph_bytes": sum(e["bytes"] for p, e in m["files"].items()
                                          if p.startswith(m["transformer"]["file"]))},
    }
    report["onnxruntime"] = bench_onnxruntime(b, prompt, params, seed, threads, warmup, text_runs)
    models = load_torch_models(b, torch_state) if use_torch else None
    if models is not None:
        report["torch"] = bench_torch(models, prompt, params, seed, threads, warmup, text_runs, no_cache)
        del models
    else:
        report["torch"] = None
        report["torch_note"] = "no PyTorch weights for this bundle" if use_torch else "skipped (--no-torch)"
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
