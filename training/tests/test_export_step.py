"""The exported ONNX step graph: static interface, tract-friendly ops, and the same
logits, cache rows and tokens as the PyTorch step."""

import numpy as np
import onnx
import pytest
import torch

from comgrasp_train.export.step_graph import (
    FORBIDDEN_OPS,
    OPSET,
    OnnxStepRunner,
    export_step_onnx,
    input_names,
    output_names,
)
from comgrasp_train.models.gpt_configs import STREAMS, preset
from comgrasp_train.models.sampling import SamplingParams, generate, run_sampling_loop
from comgrasp_train.models.transformer import ComGraspTransformer

CFG = preset("tiny")


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    model = ComGraspTransformer(CFG).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.15)
    d = tmp_path_factory.mktemp("step")
    specs = {b: export_step_onnx(model, d / f"step_b{b}.onnx", batch=b) for b in (1, 2)}
    return model, d, specs


def _dims(value_info):
    return tuple(d.dim_value for d in value_info.type.tensor_type.shape.dim)


def test_graph_interface_is_static_and_tract_friendly(exported):
    _, d, specs = exported
    for b, spec in specs.items():
        g = onnx.load(str(d / f"step_b{b}.onnx"))
        onnx.checker.check_model(g)
        assert g.opset_import[0].version == OPSET
        assert [i.name for i in g.graph.input] == input_names()
        assert [o.name for o in g.graph.output] == output_names()
        assert [(n, s) for n, _, s in spec["inputs"]] == [(i.name, _dims(i)) for i in g.graph.input]
        assert [(n, s) for n, _, s in spec["outputs"]] == [(o.name, _dims(o)) for o in g.graph.output]
        assert all(x > 0 for _, _, s in spec["inputs"] + spec["outputs"] for x in s)
        assert not {n.op_type for n in g.graph.node} & FORBIDDEN_OPS
    assert specs[2]["inputs"][3] == ("cache_k_global", "float32", (CFG.n_layers, 2, CFG.n_heads,
                                                                    CFG.block_size, CFG.head_dims[0]))


def test_onnx_step_matches_pytorch_step(exported):
    model, d, _ = exported
    b = 2
    text = torch.randn(b, CFG.d_text, generator=torch.Generator().manual_seed(3))
    runner = OnnxStepRunner(d / "step_b2.onnx", CFG, text.numpy())
    cache = model.new_cache(b)
    g = torch.Generator().manual_seed(4)
    tokens = torch.tensor(CFG.pad_ids).expand(b, 4)
    with torch.no_grad():
        for pos in range(8):
            ref_logits, ref_k, ref_v = model.step(tokens, pos, text, cache.k, cache.v)
            cache.write(pos, ref_k, ref_v)
            logits = runner.step_fn(tokens.numpy(), pos)
            for got, ref in zip(logits, ref_logits):
                assert np.abs(got - ref.numpy()).max() <= 1e-4
            for s, name in enumerate(STREAMS):  # the rows the runner wrote == PyTorch's
                assert np.abs(runner.cache[f"cache_k_{name}"] - cache.k[s].numpy()).max() <= 1e-4
                assert np.abs(runner.cache[f"cache_v_{name}"] - cache.v[s].numpy()).max() <= 1e-4
            tokens = torch.stack([torch.randint(0, j, (b,), generator=g) for j in CFG.codebook_sizes], 1)


@pytest.mark.parametrize("params", [SamplingParams(temperature=0.0),
                                    SamplingParams(temperature=1.0, top_k=6, min_len=8)])
def test_onnx_decoding_gives_the_same_tokens(exported, params):
    model, d, _ = exported
    text = torch.randn(1, CFG.d_text, generator=torch.Generator().manual_seed(5))
    ref = generate(model, text, params, seed=42)
    runner = OnnxStepRunner(d / "step_b1.onnx", CFG, text.numpy())
    got = run_sampling_loop(runner.step_fn, CFG, 1, params, [42])
    assert torch.equal(got.lengths, ref.lengths) and torch.equal(got.tokens, ref.tokens)
    assert int(ref.lengths[0]) >= 2
