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
