"""Component VQ-VAEs: configs, quantizer state, streaming == offline decoding, the loss."""

from __future__ import annotations

import copy
import io
import json

import pytest
import torch

from comgrasp_train import skeleton as sk
from comgrasp_train.layout import CONTACT_CHANNELS, FRAME_DIM
from comgrasp_train.models import (
    ComponentVQ,
    EMAResetQuantizer,
    StreamingDecoder,
    VQConfig,
    compute_loss,
    fit_to_tokens,
    make_config,
    make_optimizer,
    vq_training_step,
)
from comgrasp_train.models.streaming import DecoderStep
from comgrasp_train.representation import features_to_joints

REST = torch.tensor(sk.DEFAULT_REST_JOINTS, dtype=torch.float32)


def joints_fn(x: torch.Tensor) -> torch.Tensor:
    return features_to_joints(x, REST.to(x.device))


def random_batch(b: int, t: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, t, FRAME_DIM, generator=g) * 0.5
    x[..., list(CONTACT_CHANNELS)] = (torch.rand(b, t, 2, generator=g) > 0.5).float()
    return x


def randomized(vq: ComponentVQ, seed: int = 0) -> ComponentVQ:
    """Non-trivial parameters and codebooks (pad, attention bias, ... are zero at init)."""
    torch.manual_seed(seed)
    with torch.no_grad():
        for p in vq.parameters():
            p.add_(torch.randn_like(p) * 0.05)
        for part in vq.parts.values():
            part.quantizer.codebook.normal_()
            part.quantizer.initialised.fill_(True)
    return vq.eval()


# ---------------------------------------------------------------- configs


def test_presets_and_json_round_trip(tmp_path):
    d = make_config("default").model.components
    assert [(c.name, c.codebook_size, c.code_dim) for c in d] == [
        ("global", 512, 128), ("body", 1024, 256), ("lhand", 512, 192), ("rhand", 512, 192)]
    s, b = make_config("small").model.components, make_config("big").model.components
    assert all(x.codebook_size * 2 == y.codebook_size and x.code_dim * 2 == y.code_dim for x, y in zip(s, d))
    assert all(x.codebook_size * 2 == y.codebook_size and x.code_dim * 2 == y.code_dim for x, y in zip(d, b))
    for cfg in (make_config("default"), make_config("tiny", single=True, down_t=2, causal_decoder=False)):
        cfg.save_json(tmp_path / "vq.json")
        assert VQConfig.load_json(tmp_path / "vq.json") == cfg
    bad = cfg.to_dict()
    bad["model"]["down_tt"] = 3
    with pytest.raises(ValueError, match="down_tt"):
        VQConfig.from_dict(json.loads(json.dumps(bad)))
    with pytest.raises(ValueError):
        make_config("huge")


def test_codebook_override_changes_only_the_named_component():
    books = [(c.name, c.codebook_size, c.code_dim) for c in make_config("small", codebooks={"global": 1024}).model.components]
    assert books == [("global", 1024, 64), ("body", 512, 128), ("lhand", 256, 96), ("rhand", 256, 96)]
    for bad in ({"globl": 1024}, {"global": 1}):
        with pytest.raises(ValueError, match="codebook override"):
            make_config("small", codebooks=bad)


def test_validation_reads_whole_sequences_and_legacy_configs_keep_windows():
    from comgrasp_train.dataset import FeatureSet
    from comgrasp_train.normalization import Normalizer
    from comgrasp_train.train.vq_trainer import _val_batches

    lengths = (37, 80, 21)
    g = torch.Generator().manual_seed(3)
    feats = [random_batch(1, n, seed=i)[0].numpy() for i, n in enumerate(lengths)]
    fs = FeatureSet(30.0, feats, [sk.DEFAULT_REST_JOINTS] * 3, [["t"]] * 3, [{"subject": f"s{i}"} for i in range(3)])
    norm = Normalizer(mean=torch.randn(FRAME_DIM, generator=g).numpy(), std=torch.rand(FRAME_DIM, generator=g).numpy() + 0.5)
    cfg = make_config("tiny", down_t=2)  # 4 frames per token
    whole = _val_batches(fs, norm, cfg)
    assert [tuple(x.shape) for x, _ in whole] == [(1, 40, FRAME_DIM), (1, 80, FRAME_DIM), (1, 24, FRAME_DIM)]
    for (x, rest), f in zip(whole, feats):
        n = len(f)
        assert torch.allclose(x[0, :n], torch.from_numpy(norm.normalize(f)), atol=1e-6)
        assert torch.equal(x[0, n:], x[0, n - 1:n].expand(x.shape[1] - n, -1))  # the last frame held
        assert rest.shape == (1, 55, 3)
    d = cfg.to_dict()
    del d["train"]["val_sequences"]
    legacy = VQConfig.from_dict(d)
    assert legacy.train.val_sequences == 0
    windows = _val_batches(fs, norm, legacy)
    assert sum(len(x) for x, _ in windows) == legacy.train.val_windows
    assert {x.shape[1] for x, _ in windows} == {legacy.train.window_frames}


def test_object_loss_charges_only_the_global_component_and_adds_its_weighted_term():
    from dataclasses import replace

    from comgrasp_train.models.vq_losses import object_points

    x = random_batch(2, 8)
    x[..., 9:15] = torch.tensor([1.0, 0, 0, 0, 1, 0])  # identity 6D
    pts = object_points(x)
    assert torch.allclose(pts[..., 1:, :] - pts[..., :1, :], 0.1 * torch.eye(3).expand(2, 8, 3, 3))
    cfg = make_config("tiny", down_t=2)
    cfg = replace(cfg, loss=replace(cfg.loss, lambda_obj=10.0))
    vq = randomized(ComponentVQ(cfg.model))
    _, m = compute_loss(vq, x, joints_fn, cfg)
    assert m["obj/global"] > 0 and all(m[f"obj/{c}"] == 0 for c in ("body", "lhand", "rhand"))
    _, off = compute_loss(vq, x, joints_fn, make_config("tiny", down_t=2))
    assert float(off["obj"]) == 0 and torch.allclose(m["loss/global"] - off["loss/global"], 10 * m["obj/global"])


def test_hand_axes_turn_with_the_hand_and_the_hand_loss_charges_only_the_arm():
    from dataclasses import replace

    from comgrasp_train.models.vq_losses import HAND_LEVER, hand_axes
    from comgrasp_train.rotations import axis_angle_to_matrix

    j = joints_fn(random_batch(3, 4, seed=5))
    a = hand_axes(j)  # (3, 4, 2, 3, 3)
    eye = torch.eye(3).expand_as(a)
    torch.testing.assert_close(a @ a.transpose(-1, -2), eye, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(a), torch.ones(a.shape[:-2]), atol=1e-5, rtol=0)
    # A pour: the right hand (every joint below its wrist) turns 60 deg about its own long
    # axis. Its long axis stays, its other two turn by 60 deg, the left hand's frame stays,
    # and the knuckles move little: the mean joint error is a fraction of the hand term.
    w = sk.RIGHT_WRIST
    below = [i for i in range(55) if i != w and w in _ancestors(i)]
    rot = axis_angle_to_matrix(a[..., 1, 0, :] * torch.pi / 3)  # (3, 4, 3, 3)
    turned = j.clone()
    turned[..., below, :] = (j[..., below, :] - j[..., w:w + 1, :]) @ rot.transpose(-1, -2) + j[..., w:w + 1, :]
    b = hand_axes(turned)
    torch.testing.assert_close(b[..., 0, :, :], a[..., 0, :, :])
    cos = (a[..., 1, :, :] * b[..., 1, :, :]).sum(-1)
    torch.testing.assert_close(cos, torch.tensor([1.0, 0.5, 0.5]).expand_as(cos), atol=1e-5, rtol=0)
    assert (turned - j).abs().mean() < HAND_LEVER * (b - a).abs().mean() / 4  # 4.6 vs 34 mm
    # In the loss: the knuckles that span the frame hang from the wrist at fixed offsets, so
    # only the components that turn the wrist (global: the root; body: the arm) are charged.
    x = random_batch(2, 8)
    cfg = make_config("tiny", down_t=2)
    cfg = replace(cfg, loss=replace(cfg.loss, lambda_hand=10.0))
    vq = randomized(ComponentVQ(cfg.model))
    _, m = compute_loss(vq, x, joints_fn, cfg)
    assert m["hand/global"] > 0 and m["hand/body"] > 0
    assert m["hand/lhand"] == 0 and m["hand/rhand"] == 0
    _, off = compute_loss(vq, x, joints_fn, make_config("tiny", down_t=2))
    assert float(off["hand"]) == 0
    torch.testing.assert_close(m["loss/body"] - off["loss/body"], 10 * m["hand/body"])
    # "held" frames only: nothing without contact, the "all" mean when both hands hold throughout
    cont = list(CONTACT_CHANNELS)
    held = replace(cfg, loss=replace(cfg.loss, hand_loss_frames="held"))
    for flag in (0.0, 1.0):
        xc = x.clone()
        xc[..., cont] = flag
        _, h = compute_loss(vq, xc, joints_fn, held)
        _, every = compute_loss(vq, xc, joints_fn, cfg)
        torch.testing.assert_close(h["hand"], every["hand"] * flag)
    xc[..., cont] = 0.0
    xc[:, 2:5, cont[1]] = 1.0  # the right hand holds for three frames
    _, h = compute_loss(vq, xc, joints_fn, held)
    assert h["hand/body"] > 0 and h["hand/global"] > 0


def _ancestors(i: int) -> set[int]:
    out = set()
    while sk.PARENTS[i] >= 0:
        i = sk.PARENTS[i]
        out.add(i)
    return out


def test_fit_to_tokens():
    x = torch.arange(40.0).reshape(1, 20, 2)
    assert fit_to_tokens(x, 16).shape == (1, 16, 2)
    p = fit_to_tokens(x, 16, "pad")
    assert p.shape == (1, 32, 2) and torch.equal(p[0, 20:], x[0, -1:].expand(12, 2))
    with pytest.raises(ValueError):
        fit_to_tokens(x[:, :8], 16)


# ---------------------------------------------------------------- quantizer


def _train_quantizer(q: EMAResetQuantizer, batches) -> list[torch.Tensor]:
    q.train()
    return [q(x).codes for x in batches]


def test_quantizer_init_ema_and_reset():
    torch.manual_seed(0)
    q = EMAResetQuantizer(8, 4, decay=0.99)
    assert not bool(q.initialised)
    x = torch.randn(32, 4)
    q.train()(x)
    assert bool(q.initialised)
    # Every code is a vector of the first batch or an EMA average of them: near the data.
    assert torch.cdist(q.codebook, x).min(1).values.max() < 1.0
    # When the data moves away, codes no vector picks any more decay below the count
    # threshold and are reset onto encoder outputs of the current batch.
    for _ in range(400):  # a busy code's EMA count takes ~ln(count / threshold) / 0.01 steps to decay
        far = torch.randn(64, 4) + 100.0
        q(far)
    assert torch.cdist(q.codebook, far).min(1).values.max() < 3.0
    assert (q.ema_count >= q.dead_threshold(torch.tensor(64.0))).all()
    # eval mode never touches the state
    before = {k: v.clone() for k, v in q.state_dict().items()}
    q.eval()(torch.randn(16, 4))
    assert all(torch.equal(before[k], v) for k, v in q.state_dict().items())


def test_ema_warmup_finds_stale_codes_within_a_few_steps():
    """A codebook drawn from the first batch goes stale when the data moves (as the encoder
    does early in training): with the EMA warm-up every code is back on the data within 40
    steps (measured: 30); with the full decay from the start it takes 82 here, as an unused
    code is found dead only ~69 steps after its last use."""
    def stale_after(warmup: bool, steps: int) -> float:
        torch.manual_seed(0)
        q = EMAResetQuantizer(16, 4, decay=0.99, ema_warmup=warmup).train()
        q(torch.randn(64, 4))
        for _ in range(steps):
            far = torch.randn(64, 4) + 100.0
            q(far)
        return float(torch.cdist(q.codebook, far).min(1).values.max())

    assert stale_after(True, 40) < 3.0
    assert stale_after(False, 40) > 50.0
    q = EMAResetQuantizer(16, 4, ema_warmup=True).train()
    for _ in range(3):
        q(torch.randn(32, 4))
    assert int(q.ema_updates) == 3 and "ema_updates" in q.state_dict()
    # the decay grows to the configured one and stays there
    q.ema_updates.fill_(500)
    assert float(q._warmup_decay()) == pytest.approx(0.99)


def _clustered_quantizer_mse(mode: str, threshold: float, per_step: int, steps: int) -> tuple[float, int]:
    """Issue 15's reproduction: 200 clusters in 64-D (noise 0.02, MSE floor 4e-4), K=256
    codes, ``per_step`` vectors per training step. Returns (held-out MSE, distinct codes)."""
    g = torch.Generator().manual_seed(0)
    centres = torch.randn(200, 64, generator=g)

    def draw(n):
        return centres[torch.randint(0, 200, (n,), generator=g)] + 0.02 * torch.randn(n, 64, generator=g)

    torch.manual_seed(0)
    q = EMAResetQuantizer(256, 64, 0.99, threshold, mode).train()
    for _ in range(steps):
        q(draw(per_step))
    x = draw(4096)
    codes = q.eval()(x).codes
    return float(((q.dequantize(codes) - x) ** 2).mean()), int(codes.unique().numel())


def test_relative_dead_code_threshold_settles_with_few_vectors_per_step():
    """With 128 vectors per step for 256 codes the absolute threshold (1 hit per step)
    re-randomises codes in use and never reaches the floor; the relative one does."""
    mse, used = _clustered_quantizer_mse("relative", 0.1, 128, 1000)
    assert mse < 1e-2 and used >= 190, (mse, used)
    mse_abs, _ = _clustered_quantizer_mse("absolute", 1.0, 128, 1000)
    assert mse_abs > 0.1 and mse_abs > 20 * mse, (mse_abs, mse)


def test_quantizer_reports_resets_and_usage():
    q = EMAResetQuantizer(16, 4, reset_threshold=0.1).train()
    first = q(torch.randn(64, 4))
    assert 0 < float(first.used) <= 16
    # Every vector moves far away: codes nobody picks decay and get reset, and say so.
    resets = sum(float(q(torch.randn(64, 4) + 50.0).resets) for _ in range(400))
    assert resets >= 15
    assert float(q.eval()(torch.randn(8, 4)).resets) == 0.0
    with pytest.raises(ValueError, match="reset_mode"):
        EMAResetQuantizer(4, 2, reset_mode="sometimes")


def test_legacy_config_keeps_absolute_reset():
    d = make_config("tiny").to_dict()
    del d["model"]["reset_mode"]
    d["model"]["reset_threshold"] = 1.0
    del d["model"]["ema_warmup"]
    cfg = VQConfig.from_dict(d)
    assert cfg.model.reset_mode == "absolute" and not cfg.model.ema_warmup
    assert make_config("tiny").model.reset_mode == "relative" and make_config("tiny").model.ema_warmup
    # ... and the checkpoints of such a config load: no warm-up buffer
    assert "parts.body.quantizer.ema_updates" not in ComponentVQ(cfg.model).state_dict()


def test_quantizer_state_survives_save_load_and_resume():
    batches = [torch.randn(40, 6) * (1 + i) for i in range(6)]
    torch.manual_seed(1)
    q = EMAResetQuantizer(16, 6)
    _train_quantizer(q, batches[:3])
    buf = io.BytesIO()
    torch.save(q.state_dict(), buf)
    buf.seek(0)
    q2 = EMAResetQuantizer(16, 6)
    q2.load_state_dict(torch.load(buf))
    assert set(q.state_dict()) == {"codebook", "ema_sum", "ema_count", "initialised"}
    for k, v in q.state_dict().items():
        assert torch.equal(v, q2.state_dict()[k]), k
    probe = torch.randn(50, 6)
    assert torch.equal(q.eval()(probe).codes, q2.eval()(probe).codes)
    # Resume: the same batches and RNG give bit-identical codes and EMA state (no re-init).
    torch.manual_seed(7)
    a = _train_quantizer(q, batches[3:])
    torch.manual_seed(7)
    b = _train_quantizer(q2, batches[3:])
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    for k, v in q.state_dict().items():
        assert torch.equal(v, q2.state_dict()[k]), k


def test_quantizer_distributed_path_matches_single_process(tmp_path):
    """A 1-rank gloo group exercises the all-reduce / broadcast branch."""
    dist = torch.distributed
    if not dist.is_available():
        pytest.skip("torch.distributed unavailable")
    batches = [torch.randn(20, 4) for _ in range(3)]
    torch.manual_seed(3)
    ref = EMAResetQuantizer(8, 4)
    _train_quantizer(ref, batches)
    dist.init_process_group("gloo", init_method=f"file://{tmp_path}/pg", rank=0, world_size=1)
    try:
        torch.manual_seed(3)
        q = EMAResetQuantizer(8, 4)
        _train_quantizer(q, batches)
    finally:
        dist.destroy_process_group()
    for k, v in ref.state_dict().items():
        assert torch.equal(v, q.state_dict()[k]), k


# ---------------------------------------------------------------- model, streaming


@pytest.mark.parametrize("down_t", [4, 2])
def test_streaming_decode_equals_offline(down_t):
    vq = randomized(ComponentVQ(make_config("tiny", down_t=down_t).model))
    k, f = vq.context_tokens, vq.frames_per_token
    assert k == 8
    n = k + 5
    tokens = torch.stack([torch.randint(0, p.comp.codebook_size, (2, n)) for p in vq.parts.values()], 1)
    with torch.no_grad():
        offline = vq.decode(tokens)
    assert offline.shape == (2, n * f, FRAME_DIM)
    sd = StreamingDecoder(vq, batch_size=2)
    assert sd.state.shape == (2, 4, k - 1)
    chunks = [sd.step(tokens[:, :, i]) for i in range(n)]
    assert all(c.shape == (2, f, FRAME_DIM) for c in chunks)
    assert (torch.cat(chunks, 1) - offline).abs().max().item() <= 1e-4
    assert torch.equal(sd.state, tokens[:, :, -(k - 1):])


def test_receptive_field_is_exactly_k_tokens():
    """Token n's frames ignore token n-K and do depend on token n-K+1."""
    vq = randomized(ComponentVQ(make_config("tiny").model))
    k, f = vq.context_tokens, vq.frames_per_token
    n = k + 2
    tokens = torch.stack([torch.randint(0, p.comp.codebook_size, (1, n)) for p in vq.parts.values()], 1)
    last = slice((n - 1) * f, n * f)
    with torch.no_grad():
        base = vq.decode(tokens)[:, last]
        for back, changes in ((k, False), (k - 1, True)):
            t2 = tokens.clone()
            t2[:, :, n - 1 - back] = (t2[:, :, n - 1 - back] + 1) % 32
            diff = (vq.decode(t2)[:, last] - base).abs().max().item()
            assert (diff > 1e-6) == changes, (back, diff)


def test_encode_decode_shapes_and_paper_decoder():
    x = random_batch(2, 64)
    for cfg in (make_config("tiny", causal_decoder=False), make_config("tiny", single=True)):
        vq = ComponentVQ(cfg.model)
        vq.train()(x)  # initialises the codebooks
        codes = vq.eval().encode(x)
        p = len(cfg.model.components)
        assert codes.shape == (2, p, 4) and codes.dtype == torch.long
        y = vq.decode(codes)
        assert y.shape == x.shape
        c = list(CONTACT_CHANNELS)
        assert ((y[..., c] >= 0) & (y[..., c] <= 1)).all()
    with pytest.raises(ValueError, match="causal"):
        DecoderStep(ComponentVQ(make_config("tiny", causal_decoder=False).model))
    with pytest.raises(ValueError, match="multiple"):
        vq(x[:, :40])


def test_model_state_dict_round_trip_reproduces_tokens_and_frames():
    x = random_batch(2, 64, seed=1)
    vq = ComponentVQ(make_config("tiny").model)
    vq.train()(x)
    buf = io.BytesIO()
    torch.save(vq.state_dict(), buf)
    buf.seek(0)
    vq2 = ComponentVQ(make_config("tiny").model)
    vq2.load_state_dict(torch.load(buf))
    vq.eval(), vq2.eval()
    assert torch.equal(vq.encode(x), vq2.encode(x))
    with torch.no_grad():
        assert torch.equal(vq.decode(vq.encode(x)), vq2.decode(vq.encode(x)))


# ---------------------------------------------------------------- loss, training step


def test_loss_terms_and_component_isolation():
    torch.manual_seed(0)
    cfg = make_config("tiny")
    vq = ComponentVQ(cfg.model)
    x = random_batch(2, 32, seed=2)
    loss, m = compute_loss(vq, x, joints_fn, cfg)
    assert torch.isfinite(loss)
    for key in ("param", "joint", "vel", "cont", "commit", "perplexity"):
        assert {f"{key}/{n}" for n in vq.names} <= set(m), key
    assert m["param"] > 0 and m["joint"] > 0 and m["vel"] > 0
    assert m["cont/global"] == 0 and m["cont/body"] == 0 and m["cont/lhand"] > 0
    # Each component is charged only for its own slice (the joint term uses ground truth
    # elsewhere): changing the body tokenizer leaves the global tokenizer's gradients alone.
    other = copy.deepcopy(vq)
    with torch.no_grad():
        for p in other.parts["body"].parameters():
            p.add_(torch.randn_like(p))
    grads = []
    for model in (vq, other):
        model.zero_grad()
        compute_loss(model, x, joints_fn, cfg)[0].backward()
        grads.append(torch.cat([p.grad.flatten() for p in model.parts["global"].parameters()]))
    assert grads[0].abs().max() > 0
    torch.testing.assert_close(grads[0], grads[1])


def test_training_step_reduces_loss_and_handles_denormalize():
    torch.manual_seed(0)
    cfg = make_config("tiny", single=True)
    vq = ComponentVQ(cfg.model)
    opt = make_optimizer(vq, VQConfig(cfg.preset, cfg.model, cfg.loss, cfg.train.__class__(lr=2e-3)))
    x = random_batch(2, 32, seed=3)
    mean, std = torch.randn(FRAME_DIM) * 0.1, torch.rand(FRAME_DIM) + 0.5
    first = vq_training_step(vq, opt, x, joints_fn, cfg, denormalize=lambda t: t * std + mean)
    for _ in range(8):
        last = vq_training_step(vq, opt, x, joints_fn, cfg, denormalize=lambda t: t * std + mean)
    assert last["loss"] < first["loss"]
    assert "grad_norm" in last and "perplexity/all" in last


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_training_step_and_streaming_on_cuda():
    cfg = make_config("tiny")
    vq = ComponentVQ(cfg.model).cuda()
    x = random_batch(2, 64).cuda()
    m = vq_training_step(vq, make_optimizer(vq, cfg), x, joints_fn, cfg)
    assert torch.isfinite(m["loss"])
    vq.eval()
    tokens = vq.encode(x)
    sd = StreamingDecoder(vq, batch_size=2)
    frames = torch.cat([sd.step(tokens[:, :, i]) for i in range(tokens.shape[-1])], 1)
    with torch.no_grad():
        assert (frames - vq.decode(tokens)).abs().max().item() <= 1e-4


def test_streaming_step_exports_to_static_onnx(tmp_path):
    """The step graph has static shapes and explicit state in/out, and matches PyTorch
    (exported by the bundle exporter, export/decoder_graph.py)."""
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from comgrasp_train.export.decoder_graph import OnnxDecoderRunner, export_decoder_onnx, initial_state

    vq = randomized(ComponentVQ(make_config("tiny").model))
    path = tmp_path / "vq_step.onnx"
    spec = export_decoder_onnx(vq, path)
    assert spec["inputs"][0] == ("state", "int64", (1, 4, vq.context_tokens - 1))
    n = vq.context_tokens + 3
    tokens = torch.stack([torch.randint(0, p.comp.codebook_size, (1, n)) for p in vq.parts.values()], 1)
    frames = OnnxDecoderRunner(path, initial_state(vq)).decode(tokens.numpy())
    with torch.no_grad():
        assert (torch.from_numpy(frames) - vq.decode(tokens)).abs().max().item() <= 1e-4
