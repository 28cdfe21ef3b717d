"""Token sequences for Transformer training: a feature set encoded by a trained VQ, plus
the batch builder (codes, then End, then Pad; a random text variant per sequence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..dataset import FeatureSet
from ..models.gpt_configs import TransformerConfig
from ..models.vqvae import ComponentVQ, fit_to_tokens
from ..normalization import Normalizer


@dataclass
class TokenSet:
    codes: list[np.ndarray]  # (L_i, 4) int64 per sequence
    texts: list[list[str]]
    meta: list[dict]


@torch.no_grad()
def encode_feature_set(vq: ComponentVQ, fs: FeatureSet, norm: Normalizer, device="cpu") -> TokenSet:
    """Each whole sequence -> (L, 4) codes; the tail is padded with the last frame to a
    whole token so a sequence's end (the release) is kept."""
    vq.eval()
    codes = []
    for f in fs.features:
        x = torch.from_numpy(norm.normalize(f.astype(np.float32)))[None].to(device)
        x = fit_to_tokens(x, vq.frames_per_token, "pad")
        codes.append(vq.encode(x)[0].T.cpu().numpy().astype(np.int64))  # (P, L) -> (L, P)
    return TokenSet(codes, fs.texts, fs.meta)


class TokenBatcher:
    """Random batches of (text, codes); sequences longer than L_max get a random crop
    (without End, since the crop does not reach the sequence's end)."""

    def __init__(self, ts: TokenSet, cfg: TransformerConfig, embed: dict[str, torch.Tensor]):
        if not ts.codes:
            raise ValueError("the token set is empty")
        self.ts, self.cfg, self.embed = ts, cfg, embed
        self.end = torch.tensor(cfg.end_ids)
        self.pad = torch.tensor(cfg.pad_ids)

    def batch(self, batch_size: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, d_text) text embeddings and (B, T, 4) targets (codes, End, Pad)."""
        idx = torch.randint(0, len(self.ts.codes), (batch_size,), generator=gen).tolist()
        l_max = self.cfg.l_max
        starts, texts = [], []
        for i in idx:
            n = len(self.ts.codes[i])
            starts.append(int(torch.randint(0, n - l_max + 1, (1,), generator=gen)) if n > l_max else 0)
            variants = self.ts.texts[i]
            texts.append(variants[int(torch.randint(0, len(variants), (1,), generator=gen))])
        return self._assemble(idx, starts, texts)

    def fixed(self, idx: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The same, without randomness (validation): each sequence from its start, with its
        first description."""
        return self._assemble(idx, [0] * len(idx), [self.ts.texts[i][0] for i in idx])

    def _assemble(self, idx: list[int], starts: list[int], texts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        l_max = self.cfg.l_max
        rows = []
        for i, start in zip(idx, starts):
            c = torch.from_numpy(self.ts.codes[i])[start:start + l_max]
            ended = start + len(c) == len(self.ts.codes[i])
            rows.append(torch.cat([c, self.end[None]]) if ended else c)
        T = max(len(r) for r in rows)
        out = self.pad.expand(len(rows), T, 4).clone()
        for b, r in enumerate(rows):
            out[b, :len(r)] = r
        return torch.stack([self.embed[t] for t in texts]), out
