"""Coordinated four-stream Transformer: config, shapes, loss, causality, coordination,
and KV-cache steps equal to the full forward pass."""

import json

import pytest
import torch

from comgrasp_train.models.gpt_configs import PRESETS, TransformerConfig, preset
from comgrasp_train.models.transformer import ComGraspTransformer, count_parameters
from comgrasp_train.train.gpt_trainer import GPTTrainConfig, drop_text

pytestmark = pytest.mark.usefixtures("one_thread")


def _model(seed=0, std=0.1, **overrides):
    """Tiny model with larger-than-init random weights (so errors are not hidden by
    near-zero activations); eval mode."""
    torch.manual_seed(seed)
    m = ComGraspTransformer(preset("tiny", **overrides))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0.0, std)
    return m.eval()


def _tokens(cfg, batch, length, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.stack([torch.randint(0, j, (batch, length), generator=g)
                        for j in cfg.codebook_sizes], dim=-1)


def test_config_roundtrip_and_derived_ids(tmp_path):
    cfg = preset("tiny")
    assert TransformerConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    cfg.save_json(tmp_path / "gpt.json")
    assert TransformerConfig.load_json(tmp_path / "gpt.json") == cfg
    assert cfg.end_ids == cfg.codebook_sizes
    assert cfg.pad_ids == tuple(j + 1 for j in cfg.codebook_sizes)
    assert cfg.vocab_sizes == tuple(j + 2 for j in cfg.codebook_sizes)
    assert PRESETS["paper"].l_max == 74 and PRESETS["paper"].block_size == 76
    with pytest.raises(ValueError):
        TransformerConfig.from_dict({**cfg.to_dict(), "bogus": 1})
    with pytest.raises(ValueError):
        cfg.replace(widths=(33, 48, 32, 32))  # not divisible by n_heads


def test_parameter_counts():
    paper = count_parameters(PRESETS["paper"])
    assert 0.35e9 < paper < 0.5e9  # paper: ~0.4 B
    assert count_parameters(PRESETS["small"]) < 20e6
    assert count_parameters(PRESETS["tiny"]) < 0.5e6
    assert len(ComGraspTransformer(PRESETS["tiny"]).coord) == PRESETS["tiny"].n_layers - 1


def test_forward_shapes_and_loss_ignores_pad():
    m = _model()
    cfg = m.cfg
    b, t = 3, 6
    text = torch.randn(b, cfg.d_text)
    logits = m(text, _tokens(cfg, b, t))
    assert [tuple(x.shape) for x in logits] == [(b, t + 1, v) for v in cfg.vocab_sizes]

    codes = _tokens(cfg, b, t + 1)
    lengths = torch.tensor([2, 5, 7])  # sequence b: codes, End at lengths[b], then Pad
    ar = torch.arange(t + 1)[None, :, None]
    end, pad = torch.tensor(cfg.end_ids), torch.tensor(cfg.pad_ids)
    codes = torch.where(ar < lengths[:, None, None], codes, pad)
    codes = torch.where(ar == lengths[:, None, None], end, codes)
    total, per = m.loss(text, codes)
    logits = m(text, codes[:, :-1])
    for i in range(4):
        keep = codes[..., i] != cfg.pad_ids[i]
        ref = torch.nn.functional.cross_entropy(logits[i][keep], codes[..., i][keep])
        assert torch.allclose(per[i], ref, atol=1e-6)
    assert torch.allclose(total, sum(per))


def test_causal_and_coordinated():
    m = _model()
    cfg = m.cfg
    text = torch.randn(2, cfg.d_text)
    toks = _tokens(cfg, 2, 8)
    base = m(text, toks)
    # Change the body code at input index 4 (sequence position 5).
    changed = toks.clone()
    changed[:, 4, 1] = (changed[:, 4, 1] + 1) % cfg.codebook_sizes[1]
    out = m(text, changed)
    for i in range(4):
        assert torch.equal(out[i][:, :5], base[i][:, :5]), "future codes leaked into the past"
    # Coordination: the other streams see the body change at the same position.
    for i in (0, 2, 3):
        assert (out[i][:, 5] - base[i][:, 5]).abs().max() > 1e-4


def test_kv_cache_steps_equal_full_forward():
    m = _model(seed=3)
    cfg = m.cfg
    b, t = 2, cfg.block_size - 1
    text = torch.randn(b, cfg.d_text)
    toks = _tokens(cfg, b, t, seed=4)
    with torch.no_grad():
        full = m(text, toks)
        cache = m.new_cache(b)
        pad = torch.tensor(cfg.pad_ids).expand(b, 4)
        for pos in range(t + 1):
            logits = m.decode_step(toks[:, pos - 1] if pos else pad, pos, text, cache)
            for lg, f in zip(logits, full):
                assert (lg - f[:, pos]).abs().max().item() <= 1e-5


def test_trains_on_a_fixed_batch():
    torch.manual_seed(0)
    m = ComGraspTransformer(preset("tiny"))
    cfg = m.cfg
    text = torch.randn(4, cfg.d_text)
    codes = _tokens(cfg, 4, 8)
    opt = torch.optim.AdamW(m.parameters(), lr=3e-3)
    first = None
    for _ in range(40):
        loss, _ = m.loss(text, codes)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.5 * first


def test_text_dropout_zeroes_whole_rows_at_its_rate():
    """The null condition classifier-free guidance needs: rows zeroed whole at rate p, the
    others untouched; p = 0 leaves the generator's stream alone."""
    emb = torch.randn(4000, 8) + 3.0  # no row is zero by chance
    gen = torch.Generator().manual_seed(0)
    out = drop_text(emb, 0.1, gen)
    zero = (out == 0).all(dim=1)
    assert torch.equal(out[~zero], emb[~zero]) and 0.08 < zero.float().mean() < 0.12
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    assert drop_text(emb, 0.0, g1) is emb and torch.equal(torch.rand(3, generator=g1), torch.rand(3, generator=g2))
    with pytest.raises(ValueError, match="text_dropout"):
        GPTTrainConfig(text_dropout=1.0)
    assert GPTTrainConfig.from_dict({"batch_size": 8}).text_dropout == 0.0  # configs saved before it
