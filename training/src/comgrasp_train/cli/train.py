"""`comgrasp-train`: train, sample, evaluate and export the ComGrasp model.

    comgrasp-train train-vq  --data PREP --out RUN/vq  [--preset small] [--single] [--paper-decoder] [--iters N]
    comgrasp-train train-gpt --data PREP --vq RUN/vq --out RUN/gpt [--preset small] [--iters N]
    comgrasp-train generate  --vq RUN/vq --gpt RUN/gpt --text "A woman drinks from the mug" --out motion.npz
    comgrasp-train evaluate  --data PREP --vq RUN/vq [--gpt RUN/gpt] --out RUN/eval/table.md [--int8-weights]
    comgrasp-train export    --vq RUN/vq --gpt RUN/gpt --out BUNDLE [--int8-weights] [--native-text]
    comgrasp-train tune-text --out RUN/text [--bundle BUNDLE] [--steps N] [--keep K] [--anchor template]

Every run directory holds ``ckpt.pt`` (resumable: rerun the same command to continue) and
``config.json``. Multi-GPU: ``torchrun --nproc_per_node N -m comgrasp_train.cli.train train-vq ...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path


def _device(args) -> str:
    """--device, else the first CUDA device when there is one, else the CPU (as training)."""
    import torch

    return args.device or ("cuda" if torch.cuda.is_available() else "cpu")


def _sampling(args):
    from ..models.sampling import SamplingParams

    return SamplingParams(temperature=args.temperature, top_k=args.top_k, min_len=args.min_len, max_len=args.max_len,
                          guidance=args.guidance)


def _time_limit(args):
    from ..train.runtime import TimeLimit

    if args.time_budget is None and args.deadline is None:
        return None
    return TimeLimit(seconds=args.time_budget, deadline=args.deadline)


def _codebooks(specs: list[str]) -> dict[str, int]:
    """``["global=1024"]`` -> ``{"global": 1024}``."""
    out = {}
    for spec in specs:
        name, _, size = spec.partition("=")
        if not size.isdigit():
            raise ValueError(f"--codebook {spec!r}: expected COMPONENT=SIZE, e.g. global=1024")
        out[name] = int(size)
    return out


def cmd_train_vq(args) -> int:
    from ..models.configs import make_config
    from ..models.vq_losses import capped_warmup
    from ..train.vq_trainer import train_vq

    cfg = make_config(args.preset, single=args.single, down_t=args.down_t, causal_decoder=not args.paper_decoder,
                      width_scale=args.width_scale, codebooks=_codebooks(args.codebook))
    t = cfg.train
    t = replace(t, total_iters=args.iters or t.total_iters, batch_size=args.batch or t.batch_size,
                warmup_iters=capped_warmup(t.warmup_iters, args.iters or t.total_iters),
                lr=args.lr or t.lr, window_frames=args.window or t.window_frames)
    if args.lambda_joint is not None:
        cfg = replace(cfg, loss=replace(cfg.loss, lambda_joint=args.lambda_joint))
    if args.lambda_obj is not None:
        cfg = replace(cfg, loss=replace(cfg.loss, lambda_obj=args.lambda_obj))
    if args.lambda_hand is not None:
        cfg = replace(cfg, loss=replace(cfg.loss, lambda_hand=args.lambda_hand))
    if args.hand_loss_frames is not None:
        cfg = replace(cfg, loss=replace(cfg.loss, hand_loss_frames=args.hand_loss_frames))
    cfg = replace(cfg, train=t)
    m = train_vq(Path(args.data), Path(args.out), cfg, seed=args.seed, device=args.device,
                 ckpt_every=args.ckpt_every, progress=not args.quiet, stop_after=args.stop_after,
                 time_limit=_time_limit(args))
    print(json.dumps(m))
    return 0


def cmd_train_gpt(args) -> int:
    from ..models.gpt_configs import preset
    from ..models.vq_losses import capped_warmup
    from ..text_encoder import load_text_encoder
    from ..train.gpt_trainer import GPTTrainConfig, TextConfig, train_gpt
    from ..train.vq_trainer import load_vq

    _, vq_cfg, _ = load_vq(Path(args.vq))
    text = TextConfig(args.text_encoder, args.clip_checkpoint, weights=args.text_weights)
    dim = load_text_encoder(text.backend, checkpoint=text.checkpoint).dim
    cfg = preset(args.preset, codebook_sizes=tuple(c.codebook_size for c in vq_cfg.model.components), d_text=dim)
    train = GPTTrainConfig(total_iters=args.iters, batch_size=args.batch, lr=args.lr or GPTTrainConfig.lr,
                           warmup_iters=capped_warmup(GPTTrainConfig.warmup_iters, args.iters),
                           text_dropout=args.text_dropout)
    m = train_gpt(Path(args.data), Path(args.vq), Path(args.out), cfg, train, text, seed=args.seed,
                  device=args.device, ckpt_every=args.ckpt_every, progress=not args.quiet,
                  stop_after=args.stop_after, time_limit=_time_limit(args))
    print(json.dumps(m))
    return 0


def cmd_generate(args) -> int:
    import numpy as np
    import torch

    from ..inference import MotionModel
    from ..representation import features_to_params
    from ..skeleton import DEFAULT_REST_JOINTS

    model = MotionModel.load(Path(args.vq), Path(args.gpt), _device(args))
    frames = model.generate([args.text] * args.n, _sampling(args), seed=args.seed)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rest = torch.from_numpy(DEFAULT_REST_JOINTS)
    for k, x in enumerate(frames):
        path = out if args.n == 1 else out.with_name(f"{out.stem}_{k}{out.suffix}")
        p = features_to_params(x, rest)
        np.savez(path, features=x, fps=model.fps, text=args.text, seed=args.seed, **p)
        print(f"{path}: {len(x)} frames ({len(x) / model.fps:.1f} s)")
    return 0


def cmd_evaluate(args) -> int:
    from ..evaluate import (
        OUTPUTS,
        evaluate_generation,
        evaluate_ground_truth_intent,
        evaluate_reconstruction,
        summarize,
        summarize_repeats,
        write_report,
    )
    from ..inference import MotionModel
    from ..normalization import Normalizer
    from ..train.vq_trainer import load_prepared, load_vq

    outputs = tuple(o for o in args.outputs.split(",") if o)
    if not outputs or set(outputs) - set(OUTPUTS):
        raise SystemExit(f"--outputs: a comma list of {', '.join(OUTPUTS)}, got {args.outputs!r}")
    # --limit takes the subjects in turn (a split lists its sequences subject by subject)
    fs = load_prepared(Path(args.data), args.part)[0].spread(args.limit)
    vq, _, _ = load_vq(Path(args.vq), _device(args))
    if args.int8_weights:
        from ..export.bundle import fake_quantize_bundle_int8

        fake_quantize_bundle_int8(vq)
    norm = Normalizer.load(Path(args.vq) / "stats.npz")
    # One row per setting and output; the raw output keeps the setting's plain name.
    named = {"raw": "", "stage": ", contact stage"}
    rows, results = {}, {}
    for o, r in evaluate_reconstruction(vq, norm, fs, outputs=outputs).items():
        rows[f"VQ reconstruction{named[o]}"] = r
        results[f"VQ reconstruction{named[o]}"] = summarize(r)
    if args.gpt:
        model = MotionModel.load(Path(args.vq), Path(args.gpt), _device(args))
        if args.int8_weights:
            fake_quantize_bundle_int8(model.vq, model.gpt)
        for prompts in args.prompts.split(","):
            by_output = evaluate_generation(model, fs, repeats=args.repeats, params=_sampling(args), seed=args.seed,
                                            prompts=prompts, outputs=outputs)
            for o, reps in by_output.items():
                name = "generation" if prompts == "template" else f"generation, {prompts.replace('_', '-')} prompts"
                name += named[o]
                rows[name] = reps
                results[f"{name} ({args.repeats} repeats)"] = summarize_repeats(reps)
        results["ground truth (prompt checks)"] = summarize(evaluate_ground_truth_intent(fs))
    write_report(results, Path(args.out))
    if args.rows:
        # per test sequence (generation: per repeat, then per sequence), for paired comparisons
        Path(args.out).with_suffix(".rows.json").write_text(json.dumps(rows))
    print(Path(args.out).read_text())
    return 0


def cmd_export(args) -> int:
    from ..export.bundle import export_trained_bundle

    manifest = export_trained_bundle(Path(args.vq), Path(args.gpt), Path(args.out), _sampling(args), seed=args.seed,
                                     int8=args.int8_weights, text_weights=args.text_weights,
                                     native_text=args.native_text)
    size = sum(f["bytes"] for f in manifest["files"].values())
    print(f"wrote {args.out} ({len(manifest['files'])} files, {size / 2**20:.1f} MiB)")
    return 0


def cmd_tune_text(args) -> int:
    from ..export.bundle import reexport_text_encoder
    from ..export.text_encoder_export import sha256_file
    from ..export.verify import load_and_verify_bundle
    from ..text_encoder import load_text_encoder, text_weights_of
    from ..train.text_tune import CONFIG_FILE, REPORT_FILE, TUNED_FILE, TextTuneConfig, load_tuned, tune_text_encoder

    manifest = None
    if args.bundle:
        manifest = load_and_verify_bundle(args.bundle)
        te, prov = manifest["text_encoder"], manifest["provenance"]
        if (te.get("kind"), te.get("name")) != ("minilm", "all-MiniLM-L6-v2"):
            raise ValueError(f"{args.bundle}: only an all-MiniLM-L6-v2 text encoder can be tuned, not {te.get('name')!r}")
        tuned = (prov.get("text_encoder_weights") or {}).get("tuned")
        if tuned:
            done = Path(args.out) / REPORT_FILE
            if done.is_file() and json.loads(done.read_text()).get("sha256") == tuned.get("sha256"):
                print(f"{args.bundle}: its text encoder is this run's already")
                return 0
            raise ValueError(f"{args.bundle}: its text encoder is tuned already; the targets must come from the "
                             "encoder the Transformers were trained with (re-export the package's first)")
    weights = args.weights or (text_weights_of(manifest["provenance"].get("text_encoder_weights"))
                               if manifest else "int8-tok4")
    cfg = TextTuneConfig(steps=args.steps, lr=args.lr, keep=args.keep, anchor=args.anchor, wordings=args.wordings,
                         held_out=args.held_out, weights=weights, seed=args.seed)
    out = Path(args.out)
    done = out / REPORT_FILE
    if done.is_file() and json.loads((out / CONFIG_FILE).read_text()) == cfg.to_dict():
        report = json.loads(done.read_text())  # tuned already with this config: reuse it
        student = load_tuned(load_text_encoder(), out / TUNED_FILE)
        if sha256_file(out / TUNED_FILE) != report["sha256"]:
            raise ValueError(f"{out / TUNED_FILE} is not the file {done} reports (sha256 differs)")
    else:
        max_tokens = manifest["text_encoder"]["max_tokens"] if manifest else None
        student = load_text_encoder(max_tokens=max_tokens)
        report = tune_text_encoder(cfg, load_text_encoder(max_tokens=max_tokens, weights=weights), student, out,
                                   progress=not args.quiet)
    for part in ("train", "held_out"):
        b, a = report["before"].get(part), report["after"].get(part)
        if b and a:
            print(f"{part} wordings, nearest meaning: " + ", ".join(f"{k} {b[k]:.3f} -> {a[k]:.3f}" for k in b))
    if manifest is not None:
        from ..text_encoder import apply_text_weights

        apply_text_weights(student, weights)
        reexport_text_encoder(args.bundle, native="native" in manifest["text_encoder"], encoder=student,
                              tuned={"config": cfg.to_dict(), "sha256": report["sha256"],
                                     "held_out": report["after"].get("held_out")},
                              command=" ".join(["comgrasp-train", *sys.argv[1:]]))
        print(f"re-exported the tuned text encoder into {args.bundle}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="comgrasp-train", description=__doc__.split("\n")[0])
    p.add_argument("-q", "--quiet", action="store_true")
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp):
        sp.add_argument("--device", default=None, help="cuda, cuda:1, cpu (default: CUDA when available)")
        sp.add_argument("--seed", type=int, default=0)

    def pausable(sp):
        sp.add_argument("--ckpt-every", type=int, default=500)
        sp.add_argument("--stop-after", type=int, default=None,
                        help="checkpoint and stop at this step (rerun without it to continue)")
        limit = sp.add_mutually_exclusive_group()
        limit.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                           help="fit the run's length (and its learning-rate drop) to this many seconds of "
                                "training, measured on the first steps; replaces --iters")
        limit.add_argument("--deadline", type=float, default=None, metavar="UNIX_SECONDS",
                           help="as --time-budget, with the seconds left at this wall-clock time (`date +%%s`) "
                                "once loading is done: loading counts against it")

    def sampling(sp):
        sp.add_argument("--guidance", type=float, default=1.0,
                        help="classifier-free guidance scale (1: off), for a GPT trained with --text-dropout; "
                             "export writes it as the bundle's default")
        sp.add_argument("--temperature", type=float, default=1.0)
        sp.add_argument("--top-k", type=int, default=0)
        sp.add_argument("--min-len", type=int, default=2)
        sp.add_argument("--max-len", type=int, default=None)

    s = sub.add_parser("train-vq", help="train the component VQ-VAEs")
    s.add_argument("--data", required=True, help="a `comgrasp-data prepare` output folder")
    s.add_argument("--out", required=True)
    s.add_argument("--preset", default="small", choices=("tiny", "small", "default", "big"))
    s.add_argument("--single", action="store_true", help="one VQ-VAE over all 335 features (ablation)")
    s.add_argument("--paper-decoder", action="store_true", help="non-causal decoder (no streaming)")
    s.add_argument("--down-t", type=int, default=4, help="2**down_t frames per token (4: 16 frames)")
    s.add_argument("--width-scale", type=float, default=1.0, help="conv widths x this (0.25 for quick CPU runs)")
    s.add_argument("--window", type=int, default=None, help="training crop length in frames")
    s.add_argument("--codebook", action="append", default=[], metavar="COMPONENT=SIZE",
                   help="another codebook size for one component (repeatable), e.g. global=1024")
    s.add_argument("--iters", type=int, default=None)
    s.add_argument("--batch", type=int, default=None)
    s.add_argument("--lr", type=float, default=None)
    s.add_argument("--lambda-joint", type=float, default=None,
                   help="weight of the FK joint L1 (metres) against the normalized parameter L1 (default 1.0)")
    s.add_argument("--lambda-obj", type=float, default=None,
                   help="weight of the object-pose L1 (metres, four points of the object; default 0: off)")
    s.add_argument("--lambda-hand", type=float, default=None,
                   help="weight of the hand-orientation L1 (metres, points 20 cm along each hand axis; default 0)")
    s.add_argument("--hand-loss-frames", choices=("all", "held"), default=None,
                   help="frames the hand-orientation L1 covers: all (default), or those where the hand holds the object")
    pausable(s)
    common(s)
    s.set_defaults(fn=cmd_train_vq)

    s = sub.add_parser("train-gpt", help="train the coordinated Transformers on a VQ's codes")
    s.add_argument("--data", required=True)
    s.add_argument("--vq", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--preset", default="small", choices=("tiny", "small", "paper"))
    s.add_argument("--text-encoder", default="minilm", choices=("minilm", "clip"))
    s.add_argument("--clip-checkpoint", default=None, help="a Hugging Face CLIP text model folder")
    s.add_argument("--text-weights", default="fp32", choices=("fp32", "int8", "int8-tok4"),
                   help="int8: train with, and export, the text encoder's weights rounded to int8 per row; "
                        "int8-tok4: the same with the word-embedding table int4 per row")
    s.add_argument("--iters", type=int, default=20000)
    s.add_argument("--batch", type=int, default=64)
    s.add_argument("--lr", type=float, default=None)
    s.add_argument("--text-dropout", type=float, default=0.0,
                   help="share of training sequences conditioned on a zero text embedding (the null condition "
                        "of classifier-free guidance, --guidance of generate and evaluate); 0.1 is usual")
    pausable(s)
    common(s)
    s.set_defaults(fn=cmd_train_gpt)

    s = sub.add_parser("generate", help="text -> motion (.npz with 335-D frames and SMPL-X parameters)")
    s.add_argument("--vq", required=True)
    s.add_argument("--gpt", required=True)
    s.add_argument("--text", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--n", type=int, default=1)
    sampling(s)
    common(s)
    s.set_defaults(fn=cmd_generate)

    s = sub.add_parser("evaluate", help="metric suite on a test split -> Table I (Markdown + JSON)")
    s.add_argument("--data", required=True)
    s.add_argument("--vq", required=True)
    s.add_argument("--gpt", default=None)
    s.add_argument("--part", default="test")
    s.add_argument("--repeats", type=int, default=3)
    s.add_argument("--limit", type=int, default=None,
                   help="at most this many sequences, the subjects taken in turn (default: all)")
    s.add_argument("--int8-weights", action="store_true",
                   help="round the Transformer's and decoders' weights to int8 per row first, exactly as "
                        "`export --int8-weights` stores them (the model of the int8 bundle)")
    s.add_argument("--prompts", default="template",
                   help="comma list: template (each test sequence's canonical text) and/or held_out "
                        "(a wording from grab.paraphrase's held-out set)")
    s.add_argument("--outputs", default="raw,stage",
                   help="comma list: raw (the model's output) and/or stage (through the engine's contact-consistency "
                        "stage, as the engine streams by default); each gets its own rows, on the same samples")
    s.add_argument("--rows", action="store_true",
                   help="also write every sequence's metrics to OUT's stem + .rows.json (same order, same seeds)")
    s.add_argument("--out", required=True)
    sampling(s)
    common(s)
    s.set_defaults(fn=cmd_evaluate)

    s = sub.add_parser("export", help="write a model bundle for the engine")
    s.add_argument("--vq", required=True)
    s.add_argument("--gpt", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--int8-weights", action="store_true",
                   help="store the step graph's and decoder's weights as int8 per row (~4x smaller files)")
    s.add_argument("--text-weights", default=None, choices=("fp32", "int8", "int8-tok4"),
                   help="the text encoder's weight scheme (default: the one the GPT run was trained with)")
    s.add_argument("--native-text", action="store_true",
                   help="also write the text encoder's weights for the engine's native path (native/text/; "
                        "MiniLM/BERT only)")
    sampling(s)
    common(s)
    s.set_defaults(fn=cmd_export)

    s = sub.add_parser("tune-text", help="tune the text encoder so unseen wordings land on their meaning "
                                         "(train/text_tune.py); with --bundle, re-export it into that bundle")
    s.add_argument("--out", required=True, help="run folder: text_tuned.pt, config.json, report.json, log.jsonl")
    s.add_argument("--bundle", default=None,
                   help="a bundle whose Transformers were trained on the package's MiniLM: its text encoder is "
                        "replaced in place by the tuned one")
    s.add_argument("--weights", default=None, choices=("fp32", "int8", "int8-tok4"),
                   help="the text weights the Transformers were trained with (default: the bundle's, else int8-tok4)")
    s.add_argument("--steps", type=int, default=400)
    s.add_argument("--lr", type=float, default=5e-5)
    s.add_argument("--keep", type=float, default=0.0,
                   help="weight of a wording's own embedding in its target; the rest is its meaning's centroid")
    s.add_argument("--anchor", default="template", choices=("template", "centroid"),
                   help="where a meaning's wordings are pulled: its canonical template's embedding, or the mean "
                        "of its training wordings'")
    s.add_argument("--wordings", type=int, default=32, help="training paraphrases per meaning")
    s.add_argument("--held-out", type=int, default=8, help="held-out wordings per meaning for the report")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(fn=cmd_tune_text)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.fn(args)
    except (FileNotFoundError, ValueError) as e:
        print(f"comgrasp-train {args.cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
