"""`comgrasp-train evaluate --int8-weights` evaluates the model of the int8 bundle: the
weights it runs are exactly the int8 rows x scale that `export --int8-weights` writes
(scripts/precision_report.sh compares fp32 and int8 with it)."""

import numpy as np
import pytest
import torch

import comgrasp_train.evaluate as ev
import comgrasp_train.inference as inference
import comgrasp_train.train.vq_trainer as vq_trainer
from comgrasp_train.cli.train import main
from comgrasp_train.dataset import FeatureSet
from comgrasp_train.export.bundle import DECODER_FILE, STEP_FILE, decoder_state_dict, fake_quantize_bundle_int8
from comgrasp_train.export.native_weights import read_native_weights, write_native_weights
from comgrasp_train.export.tiny import tiny_gpt, tiny_normalizer, tiny_vq
from comgrasp_train.normalization import Normalizer


@pytest.fixture
def int8_bundle_weights(tmp_path):
    """The tiny models' native weights as an int8 export writes them (read back: int8 rows x
    scale), the fp32 weights, and the names stored as int8."""
    vq, gpt = tiny_vq()[0], tiny_gpt()[0]
    fp32 = {**gpt.state_dict(), **decoder_state_dict(vq)}
    fp32 = {k: v.clone() for k, v in fp32.items()}
    q = fake_quantize_bundle_int8(vq, gpt)
    step = write_native_weights(gpt.state_dict(), tmp_path, "native/step", quantized=q[STEP_FILE])
    dec = write_native_weights(decoder_state_dict(vq), tmp_path, "native/decoder", quantized=q[DECODER_FILE])
    int8 = {k for sec in (step, dec) for k, t in sec["tensors"].items() if t["dtype"] == "int8"}
    assert {w.name for ws in q.values() for w in ws} == int8 and len(q[STEP_FILE]) and len(q[DECODER_FILE])
    assert np.load(tmp_path / "native/step" / f"{q[STEP_FILE][0].name}.npy").dtype == np.int8
    return {**read_native_weights(tmp_path, step), **read_native_weights(tmp_path, dec)}, fp32, int8


def _run_evaluate(tmp_path, monkeypatch, flags: list[str]) -> dict[str, dict[str, torch.Tensor]]:
    """cmd_evaluate on fresh tiny models (no data, no metrics: the evaluation functions are
    replaced by recorders); returns the weights each evaluation ran with."""
    seen = {}

    def fresh_vq(*_a, **_k):
        return tiny_vq()[0], None, None

    def fresh_model(*_a, **_k):
        return inference.MotionModel(tiny_vq()[0], tiny_gpt()[0], None, tiny_normalizer(), 30.0, torch.device("cpu"))

    def reconstruction(vq, *_a, **_k):
        seen["reconstruction"] = decoder_state_dict(vq)
        return {o: [{"mpjpe_mm": 1.0}] for o in _k["outputs"]}

    def generation(model, *_a, **_k):
        seen["generation"] = {**model.gpt.state_dict(), **decoder_state_dict(model.vq)}
        return {o: [[{"mpjpe_mm": 1.0}]] for o in _k["outputs"]}

    monkeypatch.setattr(vq_trainer, "load_prepared", lambda *_a, **_k: (FeatureSet(30.0), None))
    monkeypatch.setattr(vq_trainer, "load_vq", fresh_vq)
    monkeypatch.setattr(Normalizer, "load", staticmethod(lambda *_a: tiny_normalizer()))
    monkeypatch.setattr(inference.MotionModel, "load", staticmethod(fresh_model))
    monkeypatch.setattr(ev, "evaluate_reconstruction", reconstruction)
    monkeypatch.setattr(ev, "evaluate_generation", generation)
    monkeypatch.setattr(ev, "evaluate_ground_truth_intent", lambda *_a, **_k: [{"intent_ok": 1.0}])
    out = tmp_path / "eval" / "table.md"
    assert main(["-q", "evaluate", "--data", "-", "--vq", "-", "--gpt", "-", "--out", str(out), *flags]) == 0
    assert out.is_file()
    return seen


def test_evaluate_int8_runs_the_exported_int8_weights(tmp_path, monkeypatch, one_thread, int8_bundle_weights):
    bundle, fp32, int8 = int8_bundle_weights
    seen = _run_evaluate(tmp_path, monkeypatch, ["--int8-weights"])
    for setting, weights in seen.items():
        for name in int8:
            if name in weights:
                assert torch.equal(weights[name], bundle[name]), (setting, name)
                assert not torch.equal(weights[name], fp32[name]), (setting, name)  # rounding changed it
        # every other tensor (biases, norms, codebooks) stays as trained
        for name, t in weights.items():
            assert torch.equal(t, bundle[name] if name in int8 else fp32.get(name, t)), (setting, name)
    assert int8 <= set(seen["generation"]) and int8 & set(seen["reconstruction"])


def test_evaluate_without_the_option_runs_fp32(tmp_path, monkeypatch, one_thread, int8_bundle_weights):
    bundle, fp32, int8 = int8_bundle_weights
    seen = _run_evaluate(tmp_path, monkeypatch, [])
    for weights in seen.values():
        assert all(torch.equal(weights[n], fp32[n]) for n in int8 if n in weights)
        assert not any(torch.equal(weights[n], bundle[n]) for n in int8 if n in weights)
