"""Component VQ-VAEs (paper Sec. III-C): encoder, quantizer, decoder, and the container of four.

Shapes: features are (B, T, D) with T a multiple of ``F = 2**down_t`` frames per token
(``fit_to_tokens`` crops or pads); tokens are (B, T / F) int64.

Decoders (DESIGN §3, deliberate deviation 1):

* ``causal_decoder=False``: the paper's T2M-GPT-style decoder; it sees the whole sequence.
* ``causal_decoder=True`` (default): a causal conv stack plus causal local attention at the
  token rate. Its receptive field is finite: the ``F`` frames of token n depend only on
  tokens n-K+1 .. n, ``K = Decoder.context_tokens`` (8 with the default architecture at
  down_t 4). Offline decoding left-pads the sequence with K-1 learned pad embeddings, so
  decoding token n from a window of its last K tokens (``ComponentVQVAE.step_window``,
  windows that start before the sequence are filled with the pad) gives exactly the same
  frames. That window is the explicit, static-shape state of the streaming step
  (``models.streaming``).

Decoder outputs are "raw": contact channels are logits (the loss takes BCE on them);
``to_features`` applies the sigmoid, so decoded features carry contact probabilities.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ..layout import FRAME_DIM
from .configs import ComponentConfig, ModelConfig
from .layers import AttentionBlock, Conv, Upsample2, res_stack
from .quantizer import EMAResetQuantizer


def fit_to_tokens(x: torch.Tensor, frames_per_token: int, mode: str = "crop") -> torch.Tensor:
    """Make the time axis (dim -2) a multiple of ``frames_per_token``.

    ``crop`` drops the trailing partial token; ``pad`` repeats the last frame (a still pose,
    not zeros, which would be a jump to the mean pose).
    """
    t = x.shape[-2]
    if mode == "crop":
        keep = t - t % frames_per_token
        if keep == 0:
            raise ValueError(f"sequence of {t} frames is shorter than one token ({frames_per_token} frames)")
        return x[..., :keep, :]
    if mode == "pad":
        extra = -t % frames_per_token
        return torch.cat([x, x[..., -1:, :].expand(*x.shape[:-2], extra, x.shape[-1])], -2) if extra else x
    raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")


class Encoder(nn.Module):
    """(B, D, T) -> (B, code_dim, T / F): strided convs + residual stacks + cross-frame attention."""

    def __init__(self, comp: ComponentConfig, cfg: ModelConfig):
        super().__init__()
        w = comp.width
        layers: list[nn.Module] = [Conv(comp.dim, w, 3), nn.ReLU()]
        for _ in range(cfg.down_t):
            layers += [nn.Conv1d(w, w, 4, stride=2, padding=1), *res_stack(w, cfg.res_depth, 3, cfg.dilation_growth, False)]
        layers += [AttentionBlock(w, cfg.attn_heads) for _ in range(cfg.enc_attn_layers)]
        layers.append(Conv(w, comp.code_dim, 3))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class Decoder(nn.Module):
    """(B, code_dim, N) -> (B, D, N * F); causal with a finite receptive field, or the paper's."""

    def __init__(self, comp: ComponentConfig, cfg: ModelConfig):
        super().__init__()
        w, causal = comp.width, cfg.causal_decoder
        k = cfg.causal_kernel if causal else 3

        def stack() -> list[nn.Module]:
            if causal:  # undilated, so the receptive field stays a few tokens
                return res_stack(w, cfg.causal_depth, k, 1, True)
            return res_stack(w, cfg.res_depth, k, cfg.dilation_growth, False)

        layers: list[nn.Module] = [Conv(comp.code_dim, w, k, causal=causal), nn.ReLU()]
        if causal and cfg.dec_attn_window > 0:
            layers.append(AttentionBlock(w, cfg.attn_heads, window=cfg.dec_attn_window))
        for _ in range(cfg.down_t):
            layers += [*stack(), Upsample2(), Conv(w, w, k, causal=causal)]
        layers += [Conv(w, w, k, causal=causal), nn.ReLU(), Conv(w, comp.dim, k, causal=causal)]
        self.layers = nn.ModuleList(layers)
        self.frames_per_token = cfg.frames_per_token
        # The token-rate stage ends at the first upsampling layer.
        self._split = next(i for i, m in enumerate(layers) if isinstance(m, Upsample2))
        self.context_tokens, self.crop_tokens = self._receptive_field() if causal else (0, 0)

    def _receptive_field(self) -> tuple[int, int]:
        """(K, C): the newest token's frames read tokens n-K+1..n; the frame-rate stage reads
        the token-stage outputs of tokens n-C+1..n. Walks the layers backwards from the
        newest token's first frame (the one that reaches furthest back)."""
        n = 1 << 20  # any token index far from the start
        pos, crop = n * self.frames_per_token, 0
        for i in reversed(range(len(self.layers))):
            layer = self.layers[i]
            pos = pos // getattr(layer, "upsample", 1) - getattr(layer, "lookback", 0)
            if i == self._split:
                crop = n - pos + 1
        return n - pos + 1, crop

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            z = layer(z)
        return z

    def newest_frames(self, z: torch.Tensor) -> torch.Tensor:
        """(B, code_dim, K) window -> (B, D, F) frames of its last token. The frame-rate
        stage only runs on the last C tokens: cheaper, and exact by the receptive field."""
        for layer in self.layers[: self._split]:
            z = layer(z)
        z = z[..., -self.crop_tokens :]
        for layer in self.layers[self._split :]:
            z = layer(z)
        return z[..., -self.frames_per_token :]


class ComponentVQVAE(nn.Module):
    """One component's tokenizer over its slice of the 335-D features."""

    def __init__(self, comp: ComponentConfig, cfg: ModelConfig):
        super().__init__()
        self.comp, self.cfg = comp, cfg
        self.encoder = Encoder(comp, cfg)
        self.quantizer = EMAResetQuantizer(comp.codebook_size, comp.code_dim, cfg.ema_decay, cfg.reset_threshold,
                                           cfg.reset_mode, cfg.ema_warmup)
        self.decoder = Decoder(comp, cfg)
        self.context_tokens = self.decoder.context_tokens
        # The learned "before the start" embedding; its token id in a step window is codebook_size.
        self.pad_embedding = nn.Parameter(torch.zeros(comp.code_dim)) if cfg.causal_decoder else None
        mask = torch.zeros(comp.dim, dtype=torch.bool)
        mask[list(comp.contact_channels)] = True
        self.register_buffer("contact_mask", mask, persistent=False)

    @property
    def pad_id(self) -> int:
        return self.comp.codebook_size

    def _latent(self, x: torch.Tensor) -> torch.Tensor:
        f = self.cfg.frames_per_token
        if x.shape[-2] % f:
            raise ValueError(f"{x.shape[-2]} frames is not a multiple of {f}; use fit_to_tokens")
        return self.encoder(x.transpose(1, 2)).transpose(1, 2)  # (B, N, d)

    def forward(self, x: torch.Tensor):
        """(B, T, D) -> (raw reconstruction (B, T, D), Quantized over the B*N latents)."""
        z = self._latent(x)
        b, n, d = z.shape
        q = self.quantizer(z.reshape(b * n, d))
        return self.decode_latent(q.x_q.reshape(b, n, d)), q

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, D) -> (B, T / F) token ids (never updates the codebook)."""
        z = self._latent(x)
        return self.quantizer.nearest(z.reshape(-1, z.shape[-1])).reshape(z.shape[:2])

    def decode_latent(self, z: torch.Tensor) -> torch.Tensor:
        """(B, N, d) code vectors -> raw (B, N * F, D), offline."""
        if self.pad_embedding is not None:
            pad = self.pad_embedding.to(z.dtype).expand(z.shape[0], self.context_tokens - 1, -1)
            z = torch.cat([pad, z], 1)
        y = self.decoder(z.transpose(1, 2)).transpose(1, 2)
        return y[:, (self.context_tokens - 1) * self.cfg.frames_per_token :] if self.pad_embedding is not None else y

    def decode(self, tokens: torch.Tensor) -> torch.Tensor:
        """(B, N) token ids -> features (B, N * F, D), contact channels as probabilities."""
        return self.to_features(self.decode_latent(self.quantizer.dequantize(tokens)))

    def step_window(self, window_ids: torch.Tensor) -> torch.Tensor:
        """(B, K) ids of the last K tokens, ``pad_id`` before the start -> features (B, F, D)
        of the newest token; equal to the same frames of ``decode``."""
        if self.pad_embedding is None:
            raise ValueError("the non-causal (paper) decoder cannot stream; set causal_decoder=True")
        table = torch.cat([self.quantizer.codebook, self.pad_embedding[None].to(self.quantizer.codebook.dtype)], 0)
        z = F.embedding(window_ids, table).transpose(1, 2)
        return self.to_features(self.decoder.newest_frames(z).transpose(1, 2))

    def to_features(self, raw: torch.Tensor) -> torch.Tensor:
        return torch.where(self.contact_mask, torch.sigmoid(raw), raw)


class VQOutput(NamedTuple):
    raw: torch.Tensor  # (B, T, 335) (or the single variant's 335) with contact logits
    commit: torch.Tensor  # (P,) commitment per component
    perplexity: torch.Tensor  # (P,)
    codes: torch.Tensor  # (B, P, N)
    resets: torch.Tensor  # (P,) codes reset by this training step
    used: torch.Tensor  # (P,) distinct codes picked in this batch


class ComponentVQ(nn.Module):
    """The four component tokenizers (or the single-VQ ablation) over the full 335-D frame."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.parts = nn.ModuleDict({c.name: ComponentVQVAE(c, cfg) for c in cfg.components})
        stops = [0] + [c.feature_slice.stop for c in cfg.components]
        if any(c.feature_slice.start != s for c, s in zip(cfg.components, stops)) or stops[-1] != FRAME_DIM:
            raise ValueError("component slices must tile the frame in order")  # so outputs concatenate
        ks = {p.context_tokens for p in self.parts.values()}
        assert len(ks) == 1, "all components share the decoder architecture, hence K"
        self.context_tokens = ks.pop()
        mask = torch.zeros(len(cfg.components), FRAME_DIM, dtype=torch.bool)
        for i, c in enumerate(cfg.components):
            mask[i, c.feature_slice] = True
        self.register_buffer("component_mask", mask, persistent=False)  # (P, 335)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.parts)

    @property
    def frames_per_token(self) -> int:
        return self.cfg.frames_per_token

    def _split(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x[..., p.comp.feature_slice] for p in self.parts.values()]

    def forward(self, x: torch.Tensor) -> VQOutput:
        """(B, T, 335) normalized features -> reconstruction and quantizer statistics."""
        outs = [part(xc) for part, xc in zip(self.parts.values(), self._split(x))]
        raw = torch.cat([o[0] for o in outs], -1)
        qs = [o[1] for o in outs]
        b = x.shape[0]
        return VQOutput(
            raw,
            torch.stack([q.commit for q in qs]),
            torch.stack([q.perplexity for q in qs]),
            torch.stack([q.codes.reshape(b, -1) for q in qs], 1),
            torch.stack([q.resets for q in qs]),
            torch.stack([q.used for q in qs]),
        )

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, 335) -> (B, P, T / F) token ids, components in ``names`` order."""
        return torch.stack([part.encode(xc) for part, xc in zip(self.parts.values(), self._split(x))], 1)

    def decode(self, tokens: torch.Tensor) -> torch.Tensor:
        """(B, P, N) token ids -> (B, N * F, 335) normalized features (contact = probability)."""
        return torch.cat([part.decode(tokens[:, i]) for i, part in enumerate(self.parts.values())], -1)

    def to_features(self, raw: torch.Tensor) -> torch.Tensor:
        return torch.cat([part.to_features(r) for part, r in zip(self.parts.values(), self._split(raw))], -1)


def build_vq(cfg: ModelConfig, device: torch.device | str | None = None) -> ComponentVQ:
    """The model on ``device`` (default: CUDA when available, else CPU)."""
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return ComponentVQ(cfg).to(device)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
