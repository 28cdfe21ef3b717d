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
