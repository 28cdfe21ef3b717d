"""Random training windows over a feature set, sampled uniformly over frames.

Sequences shorter than the window are padded with their last frame (a held pose), which
keeps every sequence usable without inventing motion. Sampling draws from a
``torch.Generator`` so a resumed run continues the same stream.
"""

from __future__ import annotations

import numpy as np
import torch

from ..dataset import FeatureSet
from ..normalization import Normalizer


class WindowSampler:
    def __init__(self, fs: FeatureSet, normalizer: Normalizer, window: int):
        if len(fs) == 0:
            raise ValueError("the feature set is empty")
        self.window = window
        self.seqs = [torch.from_numpy(normalizer.normalize(f.astype(np.float32))) for f in fs.features]
        self.rest = torch.from_numpy(np.stack(fs.rest_joints).astype(np.float32))
        lengths = torch.tensor([max(1, len(f) - window + 1) for f in fs.features], dtype=torch.float64)
        self.weights = lengths / lengths.sum()

    def batch(self, batch_size: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, window, 335) normalized features and (B, 55, 3) rest joints."""
        idx = torch.multinomial(self.weights, batch_size, replacement=True, generator=gen)
        out = torch.empty(batch_size, self.window, self.seqs[0].shape[1])
        for b, i in enumerate(idx.tolist()):
            s = self.seqs[i]
            if len(s) >= self.window:
                start = int(torch.randint(0, len(s) - self.window + 1, (1,), generator=gen))
                out[b] = s[start:start + self.window]
            else:
                out[b, :len(s)] = s
                out[b, len(s):] = s[-1]
        return out, self.rest[idx]
