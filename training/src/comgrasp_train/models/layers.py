"""Building blocks of the VQ-VAEs, each tagged with how far back in time it looks.

Every temporal layer carries ``lookback``: how many past positions (at its own rate) one
output position reads when the layer is causal (0 for pointwise layers). ``Upsample2``
carries ``upsample = 2``. The causal decoder composes these tags to get its exact,
finite receptive field in tokens (see ``Decoder.context_tokens``), which is what makes a
static-shape streaming step possible. Non-causal layers are never streamed and report 0.

Everything here exports to plain ONNX ops (Conv, MatMul, Softmax, Expand, Reshape), with
no Resize and no fused attention kernels, because tract runs the graphs.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


class Conv(nn.Module):
    """Conv1d on (B, C, T), length-preserving: left (causal) or centred zero padding."""

    def __init__(self, c_in: int, c_out: int, kernel: int, dilation: int = 1, causal: bool = False):
        super().__init__()
        total = (kernel - 1) * dilation
        self.pad = (total, 0) if causal else (total // 2, total - total // 2)
        self.lookback = total if causal else 0
        self.conv = nn.Conv1d(c_in, c_out, kernel, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, self.pad))


class ResBlock(nn.Module):
    """T2M-GPT's residual unit: x + conv1x1(relu(conv_k,d(relu(x))))."""

    def __init__(self, width: int, kernel: int, dilation: int, causal: bool):
        super().__init__()
        self.conv = Conv(width, width, kernel, dilation, causal)
        self.proj = nn.Conv1d(width, width, 1)
        self.lookback = self.conv.lookback

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.proj(F.relu(self.conv(F.relu(x))))


def res_stack(width: int, depth: int, kernel: int, dilation_growth: int, causal: bool) -> list[nn.Module]:
    """``depth`` residual blocks with dilations growth**i, largest first (T2M-GPT's order)."""
    return [ResBlock(width, kernel, dilation_growth**i, causal) for i in reversed(range(depth))]


class Upsample2(nn.Module):
    """Nearest-neighbour x2 in time as Unsqueeze/Expand/Reshape (tract-friendly, no Resize)."""

    upsample = 2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, t = x.shape
        return x[..., None].expand(b, c, t, 2).reshape(b, c, 2 * t)


class AttentionBlock(nn.Module):
    """Pre-LN Transformer block over time on (B, C, T).

    ``window=0``: full, bidirectional attention (the encoder's cross-frame attention).
    ``window=W>0``: causal local attention over the last W positions (itself included)
    with a learned per-head relative-position bias, so its lookback is W - 1.
    """

    def __init__(self, width: int, heads: int, window: int = 0):
        super().__init__()
        self.heads, self.window = heads, window
        self.lookback = max(window - 1, 0)
        self.norm1 = nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.norm2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(nn.Linear(width, 2 * width), nn.GELU(), nn.Linear(2 * width, width))
        self.rel_bias = nn.Parameter(torch.zeros(heads, window)) if window > 0 else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x.transpose(1, 2)  # (B, T, C)
        h = h + self._attend(self.norm1(h))
        h = h + self.mlp(self.norm2(h))
        return h.transpose(1, 2)

    def _attend(self, h: torch.Tensor) -> torch.Tensor:
        b, t, c = h.shape
        dh = c // self.heads
        q, k, v = self.qkv(h).reshape(b, t, 3, self.heads, dh).permute(2, 0, 3, 1, 4)
        att = (q @ k.transpose(-1, -2)) * (1.0 / math.sqrt(dh))  # (B, H, T, T)
        if self.window > 0:
            pos = torch.arange(t, device=h.device)
            offset = pos[:, None] - pos[None, :]  # query - key
            allowed = (offset >= 0) & (offset < self.window)
            # where() rather than clamp(): no Clip op in the graph (tract has had Clip trouble)
            att = att + self.rel_bias[:, torch.where(allowed, offset, torch.zeros_like(offset))]
            att = att.masked_fill(~allowed, float("-inf"))
        y = att.softmax(-1) @ v  # (B, H, T, dh)
        return self.out(y.transpose(1, 2).reshape(b, t, c))
