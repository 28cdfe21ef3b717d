"""Native-path weights (export/native_weights.py, written by export_bundle beside the graphs):
they read back to the model's state_dict exactly, int8 ones to the fake-quantized values,
and the names are the ones the Rust loader looks up."""

import numpy as np
import pytest
import torch

from comgrasp_train.export.bundle import decoder_state_dict
from comgrasp_train.export.native_weights import read_native_weights, write_native_weights
from comgrasp_train.export.tiny import tiny_gpt, tiny_vq
from comgrasp_train.weight_quant import fake_quantize_int8


def _assert_same(a: dict, b: dict) -> None:
    assert set(a) == set(b)
    for k in a:
        assert a[k].shape == b[k].shape, k
        assert torch.equal(a[k].float(), b[k].float()), k


def test_float_step_weights_round_trip(tmp_path):
    gpt, _ = tiny_gpt()
    sd = gpt.state_dict()
    section = write_native_weights(sd, tmp_path, "native/step")
    assert section["dir"] == "native/step"
    assert all(t["dtype"] == "float32" for t in section["tensors"].values())
    assert "streams.0.blocks.0.attn.qkv.weight" in section["tensors"] and "slots" not in section["tensors"]
    _assert_same(read_native_weights(tmp_path, section), sd)
    # the state_dict loads back into a fresh model
    fresh, _ = tiny_gpt(seed=1)
    fresh.load_state_dict(read_native_weights(tmp_path, section))


def test_int8_step_and_decoder_weights_are_the_fake_quantized_values(tmp_path):
    gpt, _ = tiny_gpt()
    vq, _ = tiny_vq()
    step_q = fake_quantize_int8(gpt, min_numel=256)
    dec_q = [w for name, part in vq.parts.items()
             for w in fake_quantize_int8(part.decoder, min_numel=256, prefix=f"parts.{name}.decoder.")]
    assert step_q and dec_q
    step = write_native_weights(gpt.state_dict(), tmp_path, "native/step", quantized=step_q)
    dec_sd = decoder_state_dict(vq)
    dec = write_native_weights(dec_sd, tmp_path, "native/decoder", quantized=dec_q)
    for section, qs in ((step, step_q), (dec, dec_q)):
        int8 = {k for k, t in section["tensors"].items() if t["dtype"] == "int8"}
        assert int8 == {w.name for w in qs}
        for w in qs:
            base = tmp_path / section["dir"] / w.name
            assert np.load(f"{base}.npy").dtype == np.int8
            assert np.load(f"{base}.scale.npy").shape == (w.q.shape[0],)
    _assert_same(read_native_weights(tmp_path, step), gpt.state_dict())
    _assert_same(read_native_weights(tmp_path, dec), dec_sd)


def test_decoder_section_keeps_only_what_decoding_reads():
    vq, _ = tiny_vq()
    names = set(decoder_state_dict(vq))
    for part in vq.parts:
        assert f"parts.{part}.pad_embedding" in names and f"parts.{part}.quantizer.codebook" in names
        assert any(n.startswith(f"parts.{part}.decoder.") for n in names)
    assert not any(".encoder." in n or "ema_" in n or n.endswith("initialised") for n in names)


def test_mismatched_int8_names_or_values_are_refused(tmp_path):
    gpt, _ = tiny_gpt()
    q = fake_quantize_int8(gpt, min_numel=256)
    renamed = [type(w)(f"gpt.{w.name}", w.q, w.scale) for w in q]
    with pytest.raises(ValueError, match="not among the tensors"):
        write_native_weights(gpt.state_dict(), tmp_path, "a", quantized=renamed)
    other, _ = tiny_gpt(seed=2)  # not fake-quantized: the int8 rows would not be its weights
    with pytest.raises(ValueError, match="fake-quantized"):
        write_native_weights(other.state_dict(), tmp_path, "b", quantized=q)


# ----------------------------------------------------------------------------- int4 and the text encoder


@pytest.mark.parametrize("cols", [1, 2, 7, 384])
def test_int4_pack_round_trip(cols):
    from comgrasp_train.export.native_weights import pack_int4, unpack_int4

    g = np.random.default_rng(cols)
    q = g.integers(-7, 8, size=(5, cols)).astype(np.int8)
    q[0] = 7
    q[1] = -7
    p = pack_int4(q)
    assert p.dtype == np.uint8 and p.shape == (5, (cols + 1) // 2)
    assert np.array_equal(unpack_int4(p, cols), q)
    # byte j: column 2j in the low nibble, 2j + 1 in the high one, each q + 8
    assert p[0, 0] & 0x0F == 15 and p[1, 0] & 0x0F == 1
    if cols % 2:
        assert (p[:, -1] >> 4 == 8).all()  # the odd last column's missing partner is q = 0
    else:
        assert p[0, -1] >> 4 == 15


def test_int4_pack_layout_and_bounds():
    from comgrasp_train.export.native_weights import pack_int4

    assert pack_int4(np.array([[-7, 7, 0]], np.int8)).tolist() == [[1 | (15 << 4), 8 | (8 << 4)]]
    with pytest.raises(ValueError, match=r"\[-7, 7\]"):
        pack_int4(np.array([[8]], np.int8))


def test_int4_weight_round_trip(tmp_path):
    from comgrasp_train.weight_quant import fake_quantize_rows_int4

    emb = torch.nn.Embedding(11, 5)  # odd width
    (w,) = fake_quantize_rows_int4(emb, "weight")
    section = write_native_weights(emb.state_dict(), tmp_path, "t", quantized=[w])
    assert section["tensors"]["weight"] == {"dtype": "int4", "shape": [11, 5]}
    assert np.load(tmp_path / "t" / "weight.npy").shape == (11, 3)
    _assert_same(read_native_weights(tmp_path, section), emb.state_dict())


def _tiny_text(weights: str):
    from comgrasp_train.export.tiny import tiny_text_encoder
    from comgrasp_train.text_encoder import apply_text_weights

    return apply_text_weights(tiny_text_encoder(seed=1), weights, min_numel=256)


@pytest.mark.parametrize("weights", ["int8-tok4", "fp32"])
def test_native_text_reads_back_as_the_module(tmp_path, weights):
    from comgrasp_train.export.native_weights import NATIVE_TEXT_DIR, bert_native_names, write_native_text

    enc = _tiny_text(weights)
    cfg = enc.hf_model.config
    sec = write_native_text(enc, tmp_path)
    assert list(sec) == ["dir", "heads", "layer_norm_eps", "activation", "tensors"]
    assert (sec["dir"], sec["heads"], sec["layer_norm_eps"], sec["activation"]) == (
        NATIVE_TEXT_DIR, cfg.num_attention_heads, cfg.layer_norm_eps, "gelu")
    names = bert_native_names(cfg.num_hidden_layers)
    assert list(sec["tensors"]) == names and not any("position_ids" in n for n in names)
    dtypes = {n: t["dtype"] for n, t in sec["tensors"].items()}
    linear = [n for n in names if n.endswith(".weight") and (".dense." in n or ".self." in n)]
    assert linear and all(dtypes[n] == ("int8" if weights != "fp32" else "float32") for n in linear)
    assert dtypes["embeddings.word_embeddings.weight"] == ("int4" if weights != "fp32" else "float32")
    assert all(dtypes[n] == "float32" for n in names if n not in linear and "word_embeddings" not in n)
    pos = "embeddings.position_embeddings.weight"
    assert sec["tensors"][pos]["shape"] == [enc.max_tokens, cfg.hidden_size]
    # the files on disk: exactly the listed tensors (+ a scale per rounded one)
    files = sorted(p.name for p in (tmp_path / NATIVE_TEXT_DIR).iterdir())
    rounded = [n for n in names if dtypes[n] != "float32"]
    assert files == sorted([f"{n}.npy" for n in names] + [f"{n}.scale.npy" for n in rounded])
    back = read_native_weights(tmp_path, sec)
    params = dict(enc.network.named_parameters())
    for n in names:
        want = params[n].detach()[: enc.max_tokens] if n == pos else params[n].detach()
        assert torch.equal(back[n], want), n
    # the module loads them (position rows beyond max_tokens are never used) and computes the same
    full = dict(back)
    full[pos] = torch.cat([back[pos], params[pos].detach()[enc.max_tokens:]])
    fresh = _tiny_text("fp32")
    fresh.network.load_state_dict(full, strict=False)
    assert torch.equal(fresh.encode(["pick up the mug"]), enc.encode(["pick up the mug"]))


def test_native_text_refuses_what_it_cannot_describe(tmp_path):
    from types import SimpleNamespace

    from comgrasp_train.export.native_weights import write_native_text

    with pytest.raises(ValueError, match="BERT"):
        write_native_text(SimpleNamespace(network=torch.nn.Linear(2, 2), kind="clip"), tmp_path)
    enc = _tiny_text("fp32")
    enc.hf_model.config.hidden_act = "gelu_new"
    with pytest.raises(ValueError, match="GELU"):
        write_native_text(enc, tmp_path)
