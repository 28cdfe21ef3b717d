"""int8 weight storage (weight_quant.py): the fake-quantized PyTorch encoder, its ONNX file
with int8 initializers and onnxruntime must agree to fp32 rounding, and the file must
actually hold int8 tensors."""

import numpy as np
import pytest
import torch

from comgrasp_train.export.text_encoder_export import export_text_encoder
from comgrasp_train.export.tiny import tiny_text_encoder
from comgrasp_train.weight_quant import fake_quantize_int8, quantize_rows, store_int8_initializers


def test_quantize_rows_bounds_and_zero_rows():
    w = torch.tensor([[0.5, -1.0, 0.25], [0.0, 0.0, 0.0], [3.0, 1e-3, -3.0]])
    q, s = quantize_rows(w)
    assert q.dtype == np.int8 and s.dtype == np.float32
    assert np.abs(q).max() == 127 and q[1].tolist() == [0, 0, 0] and s[1] == 1.0
    err = np.abs(q * s[:, None] - w.numpy())
    assert (err <= s[:, None] / 2 + 1e-7).all()  # rounding error at most half a step per row


def test_int8_export_matches_pytorch_and_stores_int8(tmp_path):
    import onnx
    from onnx import TensorProto

    enc = tiny_text_encoder(seed=3)
    before = enc.encode(["pick up the mug"]).clone()
    enc.int8_weights = fake_quantize_int8(enc.network, min_numel=256)
    enc.clear_cache()
    assert len(enc.int8_weights) >= 5
    after = enc.encode(["pick up the mug"])
    assert 0 < float((after - before).abs().max()) < 0.05  # rounded, but close
    frag = export_text_encoder(enc, tmp_path, fragment_name=None)
    assert frag["weights"]["tensors"] == len(enc.int8_weights)
    # export_text_encoder raises above 1e-5; the recorded difference is far smaller
    assert frag["parity"]["onnxruntime_embedding_max_abs_diff"] < 1e-6
    model = onnx.load(str(tmp_path / "text_encoder.onnx"))
    int8 = [i for i in model.graph.initializer if i.data_type == TensorProto.INT8]
    assert len(int8) == len(enc.int8_weights)


def test_rewrite_refuses_a_graph_without_the_weights(tmp_path):
    enc = tiny_text_encoder(seed=4)
    export_text_encoder(enc, tmp_path, parity_prompts=None, fragment_name=None)
    stranger = fake_quantize_int8(tiny_text_encoder(seed=5).network, min_numel=256)
    with pytest.raises(RuntimeError, match="not found"):
        store_int8_initializers(tmp_path / "text_encoder.onnx", stranger)


# ----------------------------------------------------------------------------- int4 word table


def _plain_amax_int4(w: np.ndarray) -> np.ndarray:
    amax = np.abs(w).max(axis=1)
    s = np.where(amax > 0, amax / 7, 1).astype(np.float32)
    return np.clip(np.rint(w / s[:, None]), -7, 7) * s[:, None]


def test_quantize_rows_int4_bounds_error_and_zero_rows():
    from comgrasp_train.weight_quant import quantize_rows_int4

    g = np.random.default_rng(0)
    w = g.standard_normal((64, 37)).astype(np.float32) * g.uniform(0.01, 2.0, (64, 1)).astype(np.float32)
    w[5] = 0.0
    w[9, 3] = 40.0  # an outlier row: clipping it pays off
    q, s = quantize_rows_int4(w)
    assert q.dtype == np.int8 and s.dtype == np.float32 and q.shape == w.shape and s.shape == (64,)
    assert q.min() >= -7 and q.max() <= 7
    assert q[5].tolist() == [0] * 37 and s[5] == 1.0
    deq = q.astype(np.float32) * s[:, None]
    err = ((deq - w) ** 2).sum(1)
    plain = ((_plain_amax_int4(w) - w) ** 2).sum(1)
    assert (err <= plain + 1e-12).all()  # f = 1 (the plain amax scale) is among the candidates
    assert err.sum() < plain.sum()  # and usually something better is found
    # every scale is one of the candidates amax * f / 7, f in linspace(0.5, 1, 21)
    amax = np.abs(w).max(1)
    nz = amax > 0
    f = s[nz] * 7 / amax[nz]
    assert np.allclose(f, np.clip(np.round((f - 0.5) * 40) / 40 + 0.5, 0.5, 1.0), atol=1e-5)


def test_int8_tok4_rounds_only_the_word_table_and_exports_it_exactly(tmp_path):
    import onnx
    from onnx import numpy_helper

    from comgrasp_train.text_encoder import WORD_TABLE, apply_text_weights

    enc8 = apply_text_weights(tiny_text_encoder(seed=3), "int8", min_numel=256)
    enc4 = apply_text_weights(tiny_text_encoder(seed=3), "int8-tok4", min_numel=256)
    assert (enc8.weights, enc4.weights) == ("int8", "int8-tok4")
    by8 = {w.name: w for w in enc8.int8_weights}
    by4 = {w.name: w for w in enc4.int8_weights}
    assert list(by8) == list(by4) and WORD_TABLE in by4
    for name, w in by4.items():
        if name == WORD_TABLE:
            assert w.bits == 4 and w.q.dtype == np.int8 and np.abs(w.q).max() <= 7
        else:  # everything else exactly as under "int8"
            assert w.bits == 8 and np.array_equal(w.q, by8[name].q) and np.array_equal(w.scale, by8[name].scale)
    table = dict(enc4.network.named_parameters())[WORD_TABLE].detach().numpy()
    assert np.array_equal(table, by4[WORD_TABLE].dequantized())  # the module holds exactly q * scale
    # re-rounded from the int8 table: no worse than the plain amax int4 scale
    t8 = dict(enc8.network.named_parameters())[WORD_TABLE].detach().numpy()
    assert ((table - t8) ** 2).sum() <= ((_plain_amax_int4(t8) - t8) ** 2).sum()
    frag = export_text_encoder(enc4, tmp_path, fragment_name=None)
    rec = frag["weights"]
    assert rec["weights"] == "int8-tok4" and rec["int4_tensors"] == [WORD_TABLE] and "int4" in rec["scheme"]
    assert frag["parity"]["onnxruntime_embedding_max_abs_diff"] < 1e-6
    inits = {i.name: numpy_helper.to_array(i) for i in onnx.load(str(tmp_path / "text_encoder.onnx")).graph.initializer}
    stored = [a for n, a in inits.items() if n.endswith("__int8") and a.shape == by4[WORD_TABLE].q.shape]
    assert len(stored) == 1 and np.array_equal(stored[0], by4[WORD_TABLE].q)


def test_text_weights_are_checked():
    from comgrasp_train.text_encoder import apply_text_weights, text_weights_of

    with pytest.raises(ValueError, match="must be one of"):
        apply_text_weights(tiny_text_encoder(), "int4")
    enc = apply_text_weights(tiny_text_encoder(), "int8")
    with pytest.raises(ValueError, match="already rounded"):
        apply_text_weights(enc, "int8-tok4")
    # provenance.text_encoder_weights -> the scheme (bundles before the "weights" key: by the text)
    assert text_weights_of(None) == text_weights_of({"scheme": "fp32"}) == "fp32"
    assert text_weights_of({"scheme": "int8 per row, symmetric"}) == "int8"
    assert text_weights_of({"weights": "int8-tok4", "scheme": "int8 per row, ...; int4"}) == "int8-tok4"
