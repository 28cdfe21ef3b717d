"""`comgrasp-data`: make, inspect, prepare and render grasp datasets in GRAB's layout.

    comgrasp-data synth   --out DIR --sequences N --seed S [--workers W]
    comgrasp-data info    ROOT [--split NAME]
    comgrasp-data prepare ROOT --out DIR [--split NAME] [--fps 30] [--body-model open|smplx --smplx-dir D]
    comgrasp-data check   ROOT [--limit N] [--json FILE]
    comgrasp-data check-intent DATA [--part test] [--split NAME] [--limit N] [--json FILE]
    comgrasp-data render  FILE.npz --out OUT.gif|OUT.png [--strip] [--root ROOT]
    comgrasp-data text    FILE.npz [--root ROOT] [--hands]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections import Counter
from pathlib import Path


def _root_of(file: Path, root: str | None) -> Path:
    """A GRAB file lives at ROOT/grab/<subject>/<name>.npz."""
    return Path(root) if root else file.resolve().parents[2]


def _body_cfg(args):
    from ..body_model import BodyModelConfig

    return BodyModelConfig(backend=args.body_model, smplx_model_dir=args.smplx_dir)


def cmd_synth(args) -> int:
    from ..synth.generate import generate_dataset

    summary = generate_dataset(Path(args.out), args.sequences, args.seed, workers=args.workers,
                               progress=not args.quiet)
    print(json.dumps(summary, indent=1))
    return 0


def cmd_info(args) -> int:
    from ..grab.reader import load_dataset
    from ..grab.splits import get_split

    split = get_split(args.split) if args.split else None
    for part in (("train", "val", "test") if split else ("all",)):
        seqs, summary = load_dataset(args.root, split, part, progress=not args.quiet)
        frames = sum(s.n_frames for s in seqs)
        print(f"[{part}] {summary}; {frames} frames, {frames / 120 / 60:.1f} min at 120 fps")
        for key in ("intent", "obj_name", "sbj_id"):
            print(f"  {key}: " + ", ".join(f"{k} {v}" for k, v in sorted(Counter(getattr(s, key) for s in seqs).items())))
        for p in summary.problems:
            print(f"  skipped: {p}")
    return 0


def cmd_prepare(args) -> int:
    from ..dataset import prepare_features
    from ..grab.splits import get_split
    from ..normalization import Normalizer

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    split = get_split(args.split)
    stats = None
    for part in ("train", "val", "test"):
        if not split.subjects(part):
            continue
        fs, summary = prepare_features(args.root, split, part, fps=args.fps, body=_body_cfg(args),
                                       mention_hands=args.hands, progress=not args.quiet, workers=args.workers,
                                       paraphrases=args.paraphrases)
        print(f"[{part}] {summary}")
        if part == "train":
            stats = Normalizer.fit(fs.features)
            stats.save(out / "stats.npz")
        fs.save(out / f"features_{part}.npz")
    if stats is None:
        print("no training sequences: stats not written", file=sys.stderr)
        return 1
    (out / "prepare.json").write_text(json.dumps(vars(args), indent=1, default=str))
    return 0


def cmd_check(args) -> int:
    from ..plausibility import dataset_plausibility

    report = dataset_plausibility(Path(args.root), limit=args.limit, body=_body_cfg(args), fps=args.fps)
    print(json.dumps(report, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


def _feature_set(args):
    """A prepared feature file or folder (its ``--part``), or a raw GRAB-layout root
    prepared here (hands named in the texts; ``--split``/``--part``, else every sequence)."""
    from ..dataset import FeatureSet, prepare_features
    from ..grab.splits import get_split

    data = Path(args.data)
    file = data if data.suffix == ".npz" else data / f"features_{args.part}.npz"
    if file.is_file():
        return FeatureSet.load(file)
    split = get_split(args.split) if args.split else None
    return prepare_features(data, split, args.part if split else "all", fps=args.fps, body=_body_cfg(args),
                            mention_hands=True, limit=args.limit, progress=not args.quiet)[0]


def cmd_check_intent(args) -> int:
    import torch

    from ..intent_check import check_feature_set, intent_rates

    torch.set_num_threads(1)  # per-sequence FK of small tensors: extra threads only contend
    fs = _feature_set(args)
    results = check_feature_set(fs, args.limit)
    rates = intent_rates(results)
    n_ok = sum(r.ok for r in results)
    print(f"intent_ok {rates.get('intent_ok', float('nan')):.3f} ({n_ok}/{len(results)}); prompts parsed "
          f"{sum(r.intent.known for r in results)}/{len(results)}")
    print("  " + ", ".join(f"{k[len('intent_'):]} {v:.3f}" for k, v in rates.items() if k != "intent_ok"))
    failures = [{"name": fs.meta[i].get("name", str(i)), "text": fs.texts[i][0], "reason": r.reason}
                for i, r in enumerate(results) if not r.ok]
    for f in failures:
        print(f"FAIL {f['name']}: {f['text']!r}: {f['reason']}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rates": rates, "n": len(results), "failures": failures}, indent=1))
    return 0


def cmd_check_engine(args) -> int:
    """The prompt checks on the engine's own frames (``comgrasp generate --fk --out F.npz``)."""
    import numpy as np

    from ..intent_check import Intent, check_motion, object_sdf_for, parse_prompt, track_from_engine

    prompt = args.prompt
    if args.meaning:  # a wording the parser does not read: what it asks for, given
        try:
            name, obj, hands = args.meaning.split()
        except ValueError:
            print(f"comgrasp-data check-engine: error: --meaning {args.meaning!r} is not 'INTENT OBJECT HANDS'",
                  file=sys.stderr)
            return 2
        intent = Intent(name, None if hands == "none" else hands, obj)
    else:
        intent = parse_prompt(prompt)
    if not intent.known or intent.object is None:
        print(f"comgrasp-data check-engine: error: {prompt!r} is not a prompt the checker reads "
              "(use a template form, e.g. 'The woman lifts the mug with her left hand.')", file=sys.stderr)
        return 2
    results = []
    for f in args.files:
        with np.load(f) as frames:
            r = check_motion(track_from_engine(dict(frames), object_sdf_for({"object": intent.object})), intent)
        results.append({"file": f, "prompt": prompt, "ok": r.ok, "reason": r.reason, **r.row(),
                        **{k: float(v) for k, v in r.values.items()}})
        print(f"{'ok  ' if r.ok else 'FAIL'} {f}: {prompt!r}" + (f": {r.reason}" if r.reason else ""))
    keys = sorted({k for x in results for k in x if k.startswith("intent_")})
    rates = {k: float(np.mean([x[k] for x in results if k in x])) for k in keys}
    print("rates: " + ", ".join(f"{k} {v:.3f}" for k, v in rates.items()))
    if args.json:
        Path(args.json).write_text(json.dumps({"rates": rates, "n": len(results), "results": results}, indent=1))
    return 0


def cmd_render(args) -> int:
    from ..body_model import make_body_model
    from ..grab.reader import load_sequence
    from ..render import render_sequence
    from ..representation import resample_sequence

    file = Path(args.file)
    seq = resample_sequence(load_sequence(file, _root_of(file, args.root)), args.fps)
    out = render_sequence(seq, make_body_model(_body_cfg(args)), Path(args.out), fps=args.fps, strip=args.strip)
    print(out)
    return 0


def cmd_text(args) -> int:
    from ..grab.reader import load_sequence
    from ..grab.text import describe

    file = Path(args.file)
    seq = load_sequence(file, _root_of(file, args.root))
    for t in describe(seq.gender, seq.intent, seq.obj_name, seq.contact, mention_hands=args.hands):
        print(t)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="comgrasp-data", description=__doc__.split("\n")[0])
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="cmd", required=True)

    def body_args(sp):
        sp.add_argument("--body-model", default="open", choices=("open", "smplx"))
        sp.add_argument("--smplx-dir", default=None, help="folder with smplx/SMPLX_*.npz (backend smplx)")

    s = sub.add_parser("synth", help="generate the SynthGrasp dataset in GRAB's layout")
    s.add_argument("--out", required=True)
    s.add_argument("--sequences", type=int, default=1000)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--workers", type=int, default=2)
    s.set_defaults(fn=cmd_synth)

    s = sub.add_parser("info", help="count sequences, intents, objects; list skipped files")
    s.add_argument("root")
    s.add_argument("--split", default=None)
    s.set_defaults(fn=cmd_info)

    s = sub.add_parser("prepare", help="build 335-D feature sets and normalization stats for a split")
    s.add_argument("root")
    s.add_argument("--out", required=True)
    s.add_argument("--split", default="diffgrasp")
    s.add_argument("--fps", type=float, default=30.0)
    s.add_argument("--hands", action="store_true", help="name the hand(s) in the texts (SynthGrasp)")
    s.add_argument("--workers", type=int, default=2, help="processes reading and converting files")
    s.add_argument("--paraphrases", type=int, default=16,
                   help="training wordings per sequence beyond the paper's templates (grab.paraphrase); 0: templates only")
    body_args(s)
    s.set_defaults(fn=cmd_prepare)

    s = sub.add_parser("check", help="physical plausibility of a dataset's ground truth (metric suite)")
    s.add_argument("root")
    s.add_argument("--limit", type=int, default=100)
    s.add_argument("--fps", type=float, default=30.0)
    s.add_argument("--json", default=None)
    body_args(s)
    s.set_defaults(fn=cmd_check)

    s = sub.add_parser("check-intent", help="share of sequences whose motion obeys their (first) text")
    s.add_argument("data", help="a `prepare` output folder or features_*.npz, or a raw GRAB-layout root")
    s.add_argument("--part", default="test", help="which prepared part (or split part of a raw root)")
    s.add_argument("--split", default=None, help="raw root: a split name (default: every sequence)")
    s.add_argument("--limit", type=int, default=None)
    s.add_argument("--fps", type=float, default=30.0, help="raw root: the feature frame rate")
    s.add_argument("--json", default=None)
    body_args(s)
    s.set_defaults(fn=cmd_check_intent)

    s = sub.add_parser("render", help="render a sequence to an animated GIF or a PNG strip")
    s.add_argument("file")
    s.add_argument("--out", required=True)
    s.add_argument("--root", default=None, help="dataset root (default: the file's grandparent folder)")
    s.add_argument("--fps", type=float, default=15.0)
    s.add_argument("--strip", action="store_true", help="one PNG of key frames instead of a GIF")
    body_args(s)
    s.set_defaults(fn=cmd_render)

    s = sub.add_parser("check-engine", help="prompt checks on the engine's frames (comgrasp generate --fk --out F.npz)")
    s.add_argument("files", nargs="+")
    s.add_argument("--prompt", required=True, help="the prompt the files were generated from")
    s.add_argument("--meaning", default=None, metavar="'INTENT OBJECT HANDS'",
                   help="what the prompt asks for, e.g. 'pass mug left>right' (HANDS: left, right, both, "
                        "GIVER>TAKER or none; quality_report.py prompts prints it), for wordings the prompt "
                        "parser does not read")
    s.add_argument("--json", default=None)
    s.set_defaults(fn=cmd_check_engine)

    s = sub.add_parser("text", help="print the text descriptions of a sequence")
    s.add_argument("file")
    s.add_argument("--root", default=None)
    s.add_argument("--hands", action="store_true")
    s.set_defaults(fn=cmd_text)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(message)s")
    t0 = time.time()
    try:
        rc = args.fn(args)
    except (FileNotFoundError, ValueError) as e:
        print(f"comgrasp-data {args.cmd}: error: {e}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"[{args.cmd} took {time.time() - t0:.1f} s]", file=sys.stderr)
    return rc


if __name__ == "__main__":
    sys.exit(main())
