"""fp32 vs int8 weights of the default model (issue 7, point 3): token agreement, decoder
frame differences, and the Markdown report. Run by scripts/precision_report.sh, which
documents the inputs; two subcommands:

    precision_report.py tokens --vq RUN/vq --gpt RUN/gpt --data PREP --int8 BUNDLE --fp32 BUNDLE --out F.json
    precision_report.py report --dir OUT            # OUT/report.md from the JSON files in OUT

tokens: both precisions are the same checkpoints in PyTorch, int8 being the rounding
`export --int8-weights` applies (export.bundle.fake_quantize_bundle_int8), checked first
against the int8 bundle's native int8 rows (and the fp32 bundle's weights against the
checkpoints). Then, on the first PROMPTS held-out descriptions (test split) and SEEDS seeds:
sampling as the engine samples (bundle defaults: temperature 1, all tokens, End allowed from
step 2), fp32 vs int8 token streams; logits at step 0 and along the fp32 tokens (teacher
forcing); the fp32 tokens decoded by both decoders (features and FK joints). With --engine,
the release engine (`comgrasp bench --json`, End forbidden until L_max) on both bundles, per
prompt, compared with each other and with PyTorch under the same forced length.
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch


def _first_divergence(a: np.ndarray, la: int, b: np.ndarray, lb: int) -> int | None:
    """First step k where the 4 codes of a and b differ, End (at k = length) included;
    None when both streams (tokens and length) are identical."""
    n = min(la, lb)
    diff = np.nonzero((a[:n] != b[:n]).any(axis=1))[0]
    if diff.size:
        return int(diff[0])
    return None if la == lb else n


def _agreement(ta: np.ndarray, la: np.ndarray, tb: np.ndarray, lb: np.ndarray) -> dict:
    """ta/tb (B, L, 4) tokens, la/lb (B,) lengths; reference a (fp32)."""
    firsts, same_tok, n_tok, same_step = [], 0, 0, 0
    for i in range(len(la)):
        a, b = ta[i, : la[i]], tb[i, : lb[i]]
        firsts.append(_first_divergence(a, int(la[i]), b, int(lb[i])))
        n = min(len(a), len(b))
        same_tok += int((a[:n] == b[:n]).sum())
        same_step += int((a[:n] == b[:n]).all(axis=1).sum())
        n_tok += a.size  # positions of a that b lacks count as different
    div = [f for f in firsts if f is not None]
    return {
        "sequences": len(la), "identical_sequences": sum(f is None for f in firsts),
        "identical_pct": 100.0 * sum(f is None for f in firsts) / len(la),
        "tokens_compared": n_tok, "tokens_identical_pct": 100.0 * same_tok / max(1, n_tok),
        "steps_identical_pct": 100.0 * same_step / max(1, n_tok // 4),
        "same_length_pct": 100.0 * float(np.mean(la == lb)),
        "mean_length": [float(np.mean(la)), float(np.mean(lb))],
        "first_divergence": firsts,
        "first_divergence_quantiles": (np.percentile(div, [0, 25, 50, 75, 100]).tolist() if div else None),
    }


def _check_bundle_weights(model, bundle: Path, int8: bool) -> dict:
    """The PyTorch weights against a bundle's native tensors (int8 ones dequantized)."""
    from comgrasp_train.export.bundle import decoder_state_dict
    from comgrasp_train.export.native_weights import read_native_weights

    m = json.loads((bundle / "manifest.json").read_text())
    out = {}
    for sec, sd in (("transformer", model.gpt.state_dict()), ("decoder", decoder_state_dict(model.vq))):
        spec = m[sec]["native"]["tensors"]
        got = read_native_weights(bundle, m[sec]["native"])
        equal = sum(bool(torch.equal(got[k], sd[k].float().cpu())) for k in spec)
        out[sec] = {"tensors": len(spec), "int8": sum(v["dtype"] == "int8" for v in spec.values()),
                    "equal": equal}
        if equal != len(spec):
            raise SystemExit(f"{bundle}: {len(spec) - equal} {sec} tensors differ from the "
                             f"{'int8-rounded' if int8 else 'fp32'} checkpoint weights")
    return out


@torch.no_grad()
def _teacher_forced(model, emb, tokens, params, seeds) -> tuple[np.ndarray, list[torch.Tensor]]:
    """The tokens this model's sampler draws at each position of the given prefix (B, L+1, 4)
    with the same random numbers, and its logits there (per stream (B, L+1, V))."""
    from comgrasp_train.models.sampling import TokenSampler

    logits = [lg.float() for lg in model.gpt(emb, tokens)]
    sampler = TokenSampler(model.gpt.cfg, params, seeds)
    drawn = [sampler.sample([lg[:, k].numpy() for lg in logits], k) for k in range(tokens.shape[1] + 1)]
    return np.stack(drawn, axis=1), logits


@torch.no_grad()
def cmd_tokens(a) -> int:
    from comgrasp_train.export.bundle import fake_quantize_bundle_int8
    from comgrasp_train.inference import MotionModel
    from comgrasp_train.models.sampling import SamplingParams, generate
    from comgrasp_train.representation import features_to_joints
    from comgrasp_train.train.vq_trainer import load_prepared

    torch.set_num_threads(a.threads)
    fp = MotionModel.load(Path(a.vq), Path(a.gpt), "cpu")
    q = copy.deepcopy(fp)
    quantized = fake_quantize_bundle_int8(q.vq, q.gpt)
    res = {"int8_tensors": {k: len(v) for k, v in quantized.items()},
           "int8_params": {k: int(sum(w.q.size for w in v)) for k, v in quantized.items()},
           "bundle_weights": {"int8": _check_bundle_weights(q, Path(a.int8), True),
                              "fp32": _check_bundle_weights(fp, Path(a.fp32), False)}}
    man = json.loads((Path(a.int8) / "manifest.json").read_text())
    s = man["sampling"]
    params = SamplingParams(temperature=s["temperature"], top_k=s["top_k"], min_len=s["min_len"],
                            max_len=s["max_len"])
    fs, _ = load_prepared(Path(a.data), "test")
    prompts = list(dict.fromkeys(t[0] for t in fs.texts))[: a.prompts]
    emb = fp.encoder.encode(prompts)
    res["prompts"] = prompts
    res["sampling"] = {**params.to_dict(), "max_len": params.resolved_max_len(fp.gpt.cfg.l_max)}

    # step 0 logits
    lg = [[x.float() for x in m.gpt.decode_step(torch.tensor([fp.gpt.cfg.pad_ids] * len(prompts)), 0, emb,
                                                m.gpt.new_cache(len(prompts)))] for m in (fp, q)]
    res["logits_step0"] = {"max_abs_diff": max(float((x - y).abs().max()) for x, y in zip(*lg)),
                           "max_abs_logit": max(float(x.abs().max()) for x in lg[0]),
                           "max_prob_diff": max(float((x.softmax(-1) - y.softmax(-1)).abs().max())
                                                for x, y in zip(*lg))}

    runs, joints_diff, feat_diff, contact_flip, tf = [], [], [], [], []
    rest = torch.tensor(man["skeleton"]["rest_joints"], dtype=torch.float32)
    for r in range(a.seeds):
        seeds = [a.seed + 1000 * r + i for i in range(len(prompts))]
        g = [generate(m.gpt, emb, params, seeds) for m in (fp, q)]
        ag = _agreement(g[0].tokens.numpy(), g[0].lengths.numpy(), g[1].tokens.numpy(), g[1].lengths.numpy())
        runs.append({"seeds": [seeds[0], seeds[-1]], **ag})
        # teacher forcing on the fp32 tokens: logit differences and per-step flips
        L = int(g[0].lengths.max())
        toks = g[0].tokens[:, :L]
        d_fp, lf = _teacher_forced(fp, emb, toks, params, seeds)
        d_q, lq = _teacher_forced(q, emb, toks, params, seeds)
        valid = (torch.arange(L + 1)[None] <= g[0].lengths[:, None]).numpy()  # codes and the End step
        mx = max(float(((x - y).abs().amax(-1))[valid].max()) for x, y in zip(lf, lq))
        flips = (d_fp != d_q).any(-1)[valid]
        # the replay itself: fp32's draws along its own tokens must be those tokens (End at the length)
        ref = np.concatenate([toks.numpy(), np.full_like(toks.numpy()[:, :1], -1)], axis=1)
        own = ((d_fp == ref).all(-1) | (np.arange(L + 1)[None] == g[0].lengths.numpy()[:, None]))[valid]
        # per stream-step: argmax agreement, total variation and KL(fp32 || int8) of the
        # temperature-1 distributions over the whole vocabulary, fp32's entropy for scale
        am, tv, kl, ent = [], [], [], []
        for x, y in zip(lf, lq):
            x, y = x[torch.from_numpy(valid)], y[torch.from_numpy(valid)]
            px, lpx, lpy = x.softmax(-1), x.log_softmax(-1), y.log_softmax(-1)
            am.append((x.argmax(-1) == y.argmax(-1)).numpy())
            tv.append((0.5 * (px - lpy.exp()).abs().sum(-1)).numpy())
            kl.append((px * (lpx - lpy)).sum(-1).numpy())
            ent.append((-(px * lpx).sum(-1)).numpy())
        tf.append({"logits_max_abs_diff": mx, "steps": int(valid.sum()), "steps_flipped": int(flips.sum()),
                   "fp32_replay_mismatches": int((~own).sum()),
                   "stream_steps": int(sum(a.size for a in am)),
                   "argmax_agree": int(sum(int(a.sum()) for a in am)),
                   "tv_mean": float(np.concatenate(tv).mean()), "tv_max": float(np.concatenate(tv).max()),
                   "kl_mean_nats": float(np.concatenate(kl).mean()),
                   "entropy_mean_nats": float(np.concatenate(ent).mean())})
        # the same (fp32) tokens through both decoders
        for b in range(len(prompts)):
            n = int(g[0].lengths[b])
            if n == 0:
                continue
            x = [torch.from_numpy(m.decode(g[0].tokens[b], n)) for m in (fp, q)]
            j = [features_to_joints(v, rest) for v in x]
            joints_diff.append(((j[0] - j[1]).norm(dim=-1)).numpy().ravel())
            feat_diff.append(float((x[0] - x[1]).abs().max()))
            c = [v[:, [240, 334]] > 0.5 for v in x]
            contact_flip.append(float((c[0] != c[1]).float().mean()))
    # greedy decoding (temperature 0): no random draws, so token identity isolates the argmax
    greedy = SamplingParams(temperature=0.0, top_k=0, min_len=params.min_len, max_len=params.max_len)
    g = [generate(m.gpt, emb, greedy, 0) for m in (fp, q)]
    res["pytorch_greedy"] = _agreement(g[0].tokens.numpy(), g[0].lengths.numpy(), g[1].tokens.numpy(),
                                       g[1].lengths.numpy())
    jd = np.concatenate(joints_diff)
    res["pytorch_natural"] = runs
    res["teacher_forced"] = tf
    res["decoder_same_tokens"] = {
        "sequences": len(feat_diff), "joint_err_mean_m": float(jd.mean()),
        "joint_err_p99_m": float(np.percentile(jd, 99)),
        "joint_err_max_m": float(jd.max()), "feature_max_abs": max(feat_diff),
        "contact_flip_pct": 100.0 * float(np.mean(contact_flip))}

    if a.engine:
        res["engine"] = _engine(a, prompts, fp, q, emb)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


def _engine(a, prompts, fp, q, emb) -> dict:
    """comgrasp bench on both bundles per prompt (seed a.seed + i, End forbidden until L_max),
    against each other and against PyTorch with the same forced length."""
    from comgrasp_train.models.sampling import SamplingParams, generate

    toks = {}
    for name, bundle in (("fp32", a.fp32), ("int8", a.int8)):
        rows = []
        for i, p in enumerate(prompts[: a.engine_prompts]):
            out = subprocess.run([a.engine, "bench", "--bundle", bundle, "--json", "--prompt", p, "--seed",
                                  str(a.seed + i), "--warmup", "0", "--text-runs", "1", "--stream-runs", "1",
                                  "--bandwidth-mib", "0"], capture_output=True, text=True, check=True)
            r = json.loads(out.stdout)
            rows.append(r["tokens"])
            paths = r["engine_path"]
        toks[name] = np.array(rows, dtype=np.int64)
        print(f"engine {name}: {len(rows)} prompts, paths {paths}", file=sys.stderr)
    n, steps = toks["fp32"].shape[:2]
    lens = np.full(n, steps)
    res = {"prompts": n, "steps": steps, "paths": paths,
           "fp32_vs_int8": _agreement(toks["fp32"], lens, toks["int8"], lens)}
    m = json.loads((Path(a.int8) / "manifest.json").read_text())["sampling"]
    forced = SamplingParams(temperature=m["temperature"], top_k=m["top_k"], min_len=steps, max_len=steps)
    seeds = [a.seed + i for i in range(n)]
    for name, model in (("fp32", fp), ("int8", q)):
        g = generate(model.gpt, emb[:n], forced, seeds)
        same = [bool(np.array_equal(g.tokens[i].numpy(), toks[name][i])) for i in range(n)]
        res[f"engine_equals_pytorch_{name}"] = f"{sum(same)}/{n}"
    return res


# ----------------------------------------------------------------------------- report


def _fmt(x, nd=3):
    return "–" if x is None else f"{x:.{nd}f}"


def _quality_table(ev: dict, keys) -> tuple[list[str], dict]:
    """Per metric: fp32 mean ± 95% (over samples), int8 mean, Δ with its paired 95% interval,
    and for generation the reference change of fp32 itself under other seeds (repeat 2 −
    repeat 1, paired by sequence)."""
    from comgrasp_train.metrics import ci95

    lines = ["| setting | metric | fp32 (mean ± 95%, per sample) | int8 | Δ int8 − fp32 (paired 95%) | "
             "Δ fp32 other seeds (repeat 2 − 1) | abs(Δ) ≤ fp32 95% |", "|---|---|---|---|---|---|---|"]
    verdict = {}
    for setting in ("VQ reconstruction", "generation"):
        rows = {p: ev[p][setting] for p in ("fp32", "int8")}
        reps = rows["fp32"] if setting == "generation" else None
        if setting == "generation":  # repeats x sequences, flattened in the same order
            rows = {p: [x for rep in r for x in rep] for p, r in rows.items()}
        for k in keys:
            if k not in rows["fp32"][0]:
                continue
            f = np.array([r.get(k, np.nan) for r in rows["fp32"]], dtype=np.float64)
            i = np.array([r.get(k, np.nan) for r in rows["int8"]], dtype=np.float64)
            d = i - f
            ok = abs(np.nanmean(d)) <= ci95(f)
            verdict[(setting, k)] = ok
            seed = "–"
            if reps is not None and len(reps) > 1:
                s2 = np.array([r.get(k, np.nan) for r in reps[1]]) - np.array([r.get(k, np.nan) for r in reps[0]])
                seed = f"{np.nanmean(s2):+.3f} (± {ci95(s2):.3f})"
            lines.append(f"| {setting} | {k} | {np.nanmean(f):.3f} ± {ci95(f):.3f} | {np.nanmean(i):.3f} | "
                         f"{np.nanmean(d):+.3f} (± {ci95(d):.3f}) | {seed} | {'yes' if ok else 'NO'} |")
    return lines, verdict


def cmd_report(a) -> int:
    d = Path(a.dir)
    ev = {p: json.loads((d / f"eval/{p}.rows.json").read_text()) for p in ("fp32", "int8")}
    tables = {p: (d / f"eval/{p}.md").read_text().split("\n\nmean")[0] for p in ("fp32", "int8")}
    tok = json.loads((d / "tokens.json").read_text())
    bench = {p: [json.loads(f.read_text()) for f in sorted(d.glob(f"bench_{p}_*.json"))] for p in ("int8", "fp32")}
    sizes = json.loads((d / "sizes.json").read_text())
    keys = ["mpjpe_mm", "h_mpjpe_mm", "mpvpe_mm", "foot_sliding_mm", "collision_pct", "collision_depth_mm",
            "contact_f1", "contact_distance_mm", "contact_accuracy", "intent_ok"]
    qlines, verdict = _quality_table(ev, keys)
    rec = {p: np.array([r["mpjpe_mm"] for r in ev[p]["VQ reconstruction"]]) for p in ev}
    rec_d = np.abs(rec["int8"] - rec["fp32"])
    nat = tok["pytorch_natural"]
    ident = sum(r["identical_sequences"] for r in nat) / sum(r["sequences"] for r in nat) * 100
    tokpct = float(np.mean([r["tokens_identical_pct"] for r in nat]))
    div = [f for r in nat for f in r["first_divergence"] if f is not None] or [np.nan]
    eng = tok.get("engine")
    dec = tok["decoder_same_tokens"]
    tf = tok["teacher_forced"]
    flip = 100.0 * sum(t["steps_flipped"] for t in tf) / sum(t["steps"] for t in tf)

    steps = sum(t["stream_steps"] for t in tf)
    argmax = 100.0 * sum(t["argmax_agree"] for t in tf) / steps
    tv = sum(t["tv_mean"] * t["stream_steps"] for t in tf) / steps
    kl = sum(t["kl_mean_nats"] * t["stream_steps"] for t in tf) / steps
    ent = sum(t["entropy_mean_nats"] * t["stream_steps"] for t in tf) / steps
    rec_mean = float(abs(rec["int8"].mean() - rec["fp32"].mean()))
    # The bounds (docs/performance.md) and whether they hold.
    bounds = []
    for setting in ("VQ reconstruction", "generation"):
        v = [ok for (s_, _), ok in verdict.items() if s_ == setting]
        bounds.append((f"{setting}: every metric's abs(Δ mean) ≤ fp32's 95% interval (per sample, table below)",
                       f"{sum(v)}/{len(v)} metrics", all(v)))
    bounds += [
        ("VQ reconstruction: abs(Δ MPJPE), mean over sequences, ≤ 1 mm", f"{rec_mean:.3f} mm", rec_mean <= 1.0),
        ("VQ reconstruction: every sequence's abs(Δ MPJPE) ≤ 5 mm", f"max {rec_d.max():.3f} mm", rec_d.max() <= 5.0),
        ("decoder on the same tokens: every joint within 10 mm", f"max {dec['joint_err_max_m'] * 1e3:.2f} mm",
         dec["joint_err_max_m"] <= 0.01),
        ("tokens: int8's most likely token = fp32's at ≥ 99% of stream-steps (along fp32's sampled tokens)",
         f"{argmax:.2f}%", argmax >= 99.0),
        ("tokens: mean total variation between the per-step distributions ≤ 0.01", f"{tv:.4f}", tv <= 0.01),
    ]
    ok_all = all(ok for _, _, ok in bounds)
    i8, f32 = bench["int8"], bench["fp32"]

    def bn(runs, *path):  # mean over the rounds
        vals = []
        for r in runs:
            for p in path:
                r = r[p]
            vals.append(r)
        return float(np.mean(vals))

    L = []
    L += ["# fp32 vs int8 weights of the default model", "",
          "Same checkpoints (runs/default/vq, runs/default/gpt); int8 = `export --int8-weights` "
          "(step and decoder weights rounded per row, fp32 arithmetic; the text encoder is int8 in both, "
          "as the GPT was trained on it). Generated by `bash scripts/precision_report.sh`.", ""]
    bw = tok["bundle_weights"]
    L += [f"Weights checked: the int8 bundle's native tensors equal the int8-rounded checkpoint "
          f"({bw['int8']['transformer']['equal']}/{bw['int8']['transformer']['tensors']} step, "
          f"{bw['int8']['decoder']['equal']}/{bw['int8']['decoder']['tensors']} decoder; "
          f"{bw['int8']['transformer']['int8']} + {bw['int8']['decoder']['int8']} of them int8, "
          f"{sum(tok['int8_params'].values()) / 1e6:.1f} M parameters), the fp32 bundle's the checkpoint "
          f"({bw['fp32']['transformer']['equal']}/{bw['fp32']['transformer']['tensors']}, "
          f"{bw['fp32']['decoder']['equal']}/{bw['fp32']['decoder']['tensors']}).", ""]
    L += ["## Bounds (int8 is the default only if all hold)", "", "| bound | measured | holds |", "|---|---|---|"]
    L += [f"| {name} | {m} | {'yes' if ok else 'NO'} |" for name, m, ok in bounds]
    L += ["", f"**Verdict: int8 {'meets' if ok_all else 'does NOT meet'} the bounds.** Identical sampled token "
          "streams are not a bound: the sampler draws by inverse CDF, so a draw changes whenever a cumulative "
          "boundary moves past its random number, and from the first changed draw on the sequences are "
          "different samples of (nearly) the same distribution; the distributions (total variation, argmax) "
          "and the metrics are the quality measures.", ""]
    L += ["## Quality (held-out SynthGrasp test split, same seeds)", "",
          f"`comgrasp-train evaluate --limit 40 --repeats 2 --rows` without / with `--int8-weights`; "
          f"per-sample rows ({len(ev['fp32']['VQ reconstruction'])} reconstructions, "
          f"{sum(len(r) for r in ev['fp32']['generation'])} generations), paired by sequence and seed.", ""]
    L += qlines + ["", "The evaluate tables (95% over repeats for generation):", "", "fp32:", "", tables["fp32"], "",
                   "int8:", "", tables["int8"], ""]
    L += ["## Token agreement", "",
          f"{len(tok['prompts'])} held-out descriptions × {len(nat)} seeds each, the bundle's sampling "
          f"(temperature {tok['sampling']['temperature']}, top-k {tok['sampling']['top_k']}, "
          f"min_len {tok['sampling']['min_len']}, max_len {tok['sampling']['max_len']}), PyTorch, End allowed:", "",
          "| | value |", "|---|---|",
          f"| identical sequences (tokens and length) | {ident:.1f}% |",
          f"| identical tokens, position by position (over fp32's tokens) | {tokpct:.1f}% |",
          f"| same length | {np.mean([r['same_length_pct'] for r in nat]):.1f}% |",
          f"| mean length fp32 / int8 (tokens) | {np.mean([r['mean_length'][0] for r in nat]):.1f} / "
          f"{np.mean([r['mean_length'][1] for r in nat]):.1f} |",
          f"| first divergence step, quantiles 0/25/50/75/100% (diverged ones) | "
          f"{' / '.join(_fmt(x, 0) for x in np.percentile(div, [0, 25, 50, 75, 100]))} |",
          f"| step-0 logits max abs diff (largest abs logit {tok['logits_step0']['max_abs_logit']:.2f}) | "
          f"{tok['logits_step0']['max_abs_diff']:.4f} (probabilities {tok['logits_step0']['max_prob_diff']:.2e}) |",
          f"| logits along fp32 tokens, max abs diff | {max(t['logits_max_abs_diff'] for t in tf):.4f} |",
          f"| steps where int8 draws another token (same prefix, same random numbers) | {flip:.2f}% |",
          f"| most likely token equal, per stream-step (same prefix) | {argmax:.2f}% |",
          f"| total variation per stream-step, mean (same prefix) | {tv:.4f} |",
          f"| KL(fp32 ‖ int8) per stream-step, mean (fp32 entropy {ent:.3f}) | {kl:.2e} nats |",
          f"| greedy (temperature 0): identical sequences / tokens | {tok['pytorch_greedy']['identical_pct']:.1f}% / "
          f"{tok['pytorch_greedy']['tokens_identical_pct']:.1f}% |", ""]
    if eng:
        ea = eng["fp32_vs_int8"]
        L += [f"Release engine (`comgrasp bench --json`, paths {eng['paths']}), {eng['prompts']} prompts, "
              f"End forbidden until {eng['steps']} steps: identical sequences {ea['identical_pct']:.1f}%, "
              f"identical tokens {ea['tokens_identical_pct']:.1f}%, first divergence quantiles "
              f"{' / '.join(_fmt(x, 0) for x in ea['first_divergence_quantiles'] or [])}; engine tokens equal "
              f"PyTorch's: fp32 {eng['engine_equals_pytorch_fp32']}, int8 {eng['engine_equals_pytorch_int8']}.", ""]
    L += ["Same tokens through both decoders (the fp32 generations, FK with the bundle skeleton): joint "
          f"position difference mean {dec['joint_err_mean_m'] * 1e3:.3f} mm, "
          f"p99 {dec['joint_err_p99_m'] * 1e3:.3f} mm, "
          f"max {dec['joint_err_max_m'] * 1e3:.3f} mm; 335-D feature max abs {dec['feature_max_abs']:.4f}; "
          f"contact decisions flipped {dec['contact_flip_pct']:.3f}% of frames × hands.", ""]
    L += ["## Speed and size", "",
          f"`comgrasp bench --bundle B` (defaults: {i8[0]['config']['steps']} steps, prompt "
          f"\"{i8[0]['config']['prompt']}\"), int8 then fp32 back to back, {len(i8)} rounds; machine: "
          f"{i8[0]['machine']['cpu']} ({i8[0]['machine']['logical_cpus']} logical CPUs, shared), paths "
          f"{i8[0]['engine_path']}. Each value: the mean over the rounds of the bench's median.", "",
          "| | int8 (models/default) | fp32 | fp32 / int8 |", "|---|---|---|---|"]
    rows = [("token step (ms)", ("step_ms", "median")), ("decoder chunk, 16 frames (ms)", ("decode_ms", "median")),
            ("text embedding (ms)", ("text_ms", "median")),
            ("TTFF derived (ms)", ("derived", "ttff_ms")),
            ("TTFF measured stream (ms)", ("stream", "ttff_ms", "median")),
            ("RTF derived", ("derived", "rtf")), ("RTF measured stream", ("stream", "rtf", "median")),
            ("step bandwidth limit (ms, weights + KV read once)", ("bandwidth", "step_limit_int8_ms_run")),
            ("load (ms)", ("load_ms",)), ("RSS after load (MiB)", ("rss_mib", "after_load")),
            ("peak RSS (MiB)", ("rss_mib", "peak"))]
    for name, path in rows:
        x, y = bn(i8, *path), bn(f32, *path)
        L.append(f"| {name} | {x:.2f} | {y:.2f} | {y / x:.2f} |")
    for name in ("bundle", "step+decoder files"):
        x, y = sizes["int8"][name], sizes["fp32"][name]
        L.append(f"| {name} (MiB) | {x / 2**20:.1f} | {y / 2**20:.1f} | {y / x:.2f} |")
    L += ["", f"Tokens of the bench sequence: int8 sha256 {i8[0]['tokens_sha256'][:8]}…, "
          f"fp32 {f32[0]['tokens_sha256'][:8]}… (different samples: see token agreement).", ""]
    (d / "report.md").write_text("\n".join(L) + "\n")
    print((d / "report.md").read_text())
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("tokens")
    for k in ("vq", "gpt", "data", "int8", "fp32", "out"):
        t.add_argument(f"--{k}", required=True)
    t.add_argument("--prompts", type=int, default=50)
    t.add_argument("--seeds", type=int, default=2)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--engine", default=None, help="the release CLI (target/release/comgrasp); omit to skip")
    t.add_argument("--engine-prompts", type=int, default=50)
    t.set_defaults(fn=cmd_tokens)
    r = sub.add_parser("report")
    r.add_argument("--dir", required=True)
    r.set_defaults(fn=cmd_report)
    a = p.parse_args(argv)
    return a.fn(a)


if __name__ == "__main__":
    sys.exit(main())
