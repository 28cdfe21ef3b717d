"""The tiny test bundle: random weights, every contract of a real bundle, a few hundred KB.

It is the fixture of the engine's tests (and of ours): same files, same manifest, same
parity vectors as a trained bundle, only small and meaningless. Regenerate with

    python -m comgrasp_train.export.tiny --out models/tiny [--seed 0]

Contents: the 'tiny' VQ preset (with the tiny Transformer's unequal codebooks 16/32/16/24,
so an engine that assumes equal vocabularies fails), the 'tiny' Transformer preset with
d_text 32, a 1-layer random BERT (hidden 32) behind all-MiniLM-L6-v2's real tokenizer
pipeline with its vocabulary cut to the ~400 pieces the bundle's prompts, the object
names and ASCII need (the pieces keep their MiniLM order, new contiguous ids), normalization
statistics of plausible magnitude, the default skeleton and three catalogue objects.

The output is a pure function of the seed and the package versions: the bundle is
exported with one torch thread, and the provenance holds no time stamp or git commit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import string
from pathlib import Path

import numpy as np
import torch

from ..grab.text import INTENT_PHRASES, describe
from ..layout import FIELDS, FRAME_DIM
from ..models.configs import make_config
from ..models.gpt_configs import preset
from ..models.sampling import SamplingParams
from ..models.transformer import ComGraspTransformer
from ..models.vqvae import ComponentVQ
from ..normalization import Normalizer
from ..skeleton import DEFAULT_REST_JOINTS
from ..text_encoder import MiniLMTextEncoder, minilm_model_dir
from .bundle import export_bundle
from .parity import DEFAULT_STEP_PROMPTS
from .text_encoder_export import DEFAULT_PARITY_PROMPTS

OBJECTS = ("mug", "cubesmall", "waterbottle")
CODEBOOKS = (16, 32, 16, 24)
TEXT_HIDDEN, TEXT_LAYERS, TEXT_HEADS, MAX_TOKENS = 32, 1, 2, 16
SAMPLING = SamplingParams(temperature=1.0, top_k=8, min_len=4)
# With seed-0 weights this sampling seed ends both parity generations by sampling End
# (lengths 7 and 17 of max 18) while greedy runs into max_len: both stop rules are covered,
# and the decode case stays short (7 tokens).
SAMPLING_SEED = 7
SPECIALS = ("[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]")


def _corpus() -> list[str]:
    texts = list(DEFAULT_PARITY_PROMPTS) + list(DEFAULT_STEP_PROMPTS) + ["a test prompt"]
    for obj in OBJECTS:
        for intent in INTENT_PHRASES:
            for gender in ("male", "female"):
                texts += describe(gender, intent, obj)
    return texts


def tiny_tokenizer_json() -> str:
    """MiniLM's tokenizer.json restricted to the pieces of ``_corpus()`` plus ASCII characters
    (whole and as ``##`` continuations, so any ASCII word still tokenizes), re-numbered."""
    src = json.loads((minilm_model_dir() / "tokenizer.json").read_text(encoding="utf-8"))
    vocab: dict[str, int] = src["model"]["vocab"]
    from tokenizers import Tokenizer

    full = Tokenizer.from_str(json.dumps(src))
    full.no_padding()
    full.no_truncation()
    keep = set(SPECIALS)
    for e in full.encode_batch(_corpus()):
        keep.update(e.tokens)
    for c in string.ascii_lowercase + string.digits + string.punctuation:
        keep.update(t for t in (c, "##" + c) if t in vocab)
    order = sorted(keep, key=vocab.__getitem__)
    new = {t: i for i, t in enumerate(order)}
    src["model"]["vocab"] = new
    for a in src["added_tokens"]:
        a["id"] = new[a["content"]]
    for tok in src["post_processor"]["special_tokens"].values():
        tok["ids"] = [new[t] for t in tok["tokens"]]
    return json.dumps(src, ensure_ascii=False)


def tiny_text_encoder(seed: int = 0) -> MiniLMTextEncoder:
    from transformers import BertConfig, BertModel

    tok = tiny_tokenizer_json()
    cfg = BertConfig(vocab_size=len(json.loads(tok)["model"]["vocab"]), hidden_size=TEXT_HIDDEN,
                     num_hidden_layers=TEXT_LAYERS, num_attention_heads=TEXT_HEADS,
                     intermediate_size=2 * TEXT_HIDDEN, max_position_embeddings=MAX_TOKENS)
    torch.manual_seed(seed)
    bert = BertModel._from_config(cfg, attn_implementation="eager", add_pooling_layer=False)
    return MiniLMTextEncoder.from_bert(bert, tok, name="tiny-random-bert", max_tokens=MAX_TOKENS)


def _perturb(module: torch.nn.Module, scale: float, seed: int) -> None:
    """Non-trivial random weights (zero-initialised pads, biases and position tables too)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(torch.randn(p.shape, generator=g) * scale)


def random_vq_model(cfg, seed: int, perturb: float):
    """A VQ of ``cfg`` with PyTorch's initialisation (seeded), optional weight noise
    (``perturb``) and random codebooks marked initialised (shared with random_bundle.py)."""
    torch.manual_seed(seed)
    vq = ComponentVQ(cfg.model)
    if perturb:
        _perturb(vq, perturb, seed + 1)
    g = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for part in vq.parts.values():
            part.quantizer.codebook.copy_(torch.randn(part.quantizer.codebook.shape, generator=g))
            part.quantizer.initialised.fill_(True)
    return vq.eval()


def tiny_vq(seed: int = 0):
    base = make_config("tiny")
    comps = tuple(dataclasses.replace(c, codebook_size=j) for c, j in zip(base.model.components, CODEBOOKS))
    cfg = dataclasses.replace(base, model=dataclasses.replace(base.model, components=comps))
    return random_vq_model(cfg, seed, 0.05), cfg


def tiny_gpt(seed: int = 0):
    cfg = preset("tiny", d_text=TEXT_HIDDEN, codebook_sizes=CODEBOOKS)
    torch.manual_seed(seed)
    gpt = ComGraspTransformer(cfg)
    _perturb(gpt, 0.15, seed + 3)
    return gpt.eval(), cfg


def tiny_normalizer() -> Normalizer:
    """Plausible magnitudes: identity-centred 6D rotations, a pelvis about 0.9 m up, an object
    on a table in front; contact channels mean 0 / std 1 as Normalizer.fit leaves them."""
    mean, std = np.zeros(FRAME_DIM, np.float32), np.ones(FRAME_DIM, np.float32)
    for f in FIELDS:
        s = f.slice
        if f.name.endswith("rot6d"):
            mean[s] = np.tile([1, 0, 0, 0, 1, 0], f.size // 6)
            std[s] = 0.2
        elif f.name == "root_transl":
            mean[s], std[s] = (0.0, 0.0, 0.9), 0.3
        elif f.name in ("object_transl", "object_centre"):
            mean[s], std[s] = (0.0, 0.5, 0.8), 0.2
        elif f.name.endswith("wrist_to_object"):
            std[s] = 0.15
    return Normalizer(mean, std)


def make_tiny_bundle(out_dir: str | Path, seed: int = 0) -> dict:
    """Export the tiny bundle into ``out_dir`` (replacing one there); returns the manifest."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # bit-reproducible parity numbers
    try:
        vq, vq_cfg = tiny_vq(seed)
        gpt, gpt_cfg = tiny_gpt(seed)
        return export_bundle(
            out_dir, vq=vq, vq_config=vq_cfg, gpt=gpt, gpt_config=gpt_cfg, text_encoder=tiny_text_encoder(seed),
            normalizer=tiny_normalizer(), fps=30.0, sampling=SAMPLING, seed=SAMPLING_SEED,
            rest_joints=DEFAULT_REST_JOINTS, objects=OBJECTS,
            provenance={"commands": [f"python -m comgrasp_train.export.tiny --out <dir> --seed {seed}"],
                        "data": "none: random weights (test bundle)", "git": None, "training_metrics": {},
                        "note": "git commit deliberately omitted so the bundle is reproducible byte for byte"})
    finally:
        torch.set_num_threads(threads)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="models/tiny")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    m = make_tiny_bundle(a.out, a.seed)
    total = sum(f["bytes"] for f in m["files"].values()) + (Path(a.out) / "manifest.json").stat().st_size
    print(f"wrote {a.out}: {len(m['files']) + 1} files, {total / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
