"""Per-channel normalization statistics of the 335-D features over a training split.

Contact channels stay binary (mean 0, std 1) so the VQ loss can use BCE on them and the
engine can threshold them directly. Std is floored so constant channels (a joint that never
moves in a dataset) don't blow up. Saved as ``.npz`` and as plain lists for the manifest.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .layout import CONTACT_CHANNELS, FRAME_DIM

STD_FLOOR = 1e-3


@dataclass
class Normalizer:
    mean: np.ndarray  # (335,) float32
    std: np.ndarray  # (335,) float32

    @staticmethod
    def fit(features: list[np.ndarray]) -> Normalizer:
        """Statistics over all frames of all sequences (float64 accumulation)."""
        n = sum(len(f) for f in features)
        if n == 0:
            raise ValueError("cannot fit normalization statistics on an empty split")
        s = np.zeros(FRAME_DIM)
        s2 = np.zeros(FRAME_DIM)
        for f in features:
            f = f.astype(np.float64)
            s += f.sum(0)
            s2 += (f * f).sum(0)
        mean = s / n
        std = np.sqrt(np.maximum(s2 / n - mean * mean, 0.0))
        std = np.maximum(std, STD_FLOOR)
        mean[list(CONTACT_CHANNELS)] = 0.0
        std[list(CONTACT_CHANNELS)] = 1.0
        return Normalizer(mean.astype(np.float32), std.astype(np.float32))

    def normalize(self, x):
        return (x - self._like(self.mean, x)) / self._like(self.std, x)

    def denormalize(self, x):
        return x * self._like(self.std, x) + self._like(self.mean, x)

    @staticmethod
    def _like(a: np.ndarray, x):
        if isinstance(x, torch.Tensor):
            return torch.as_tensor(a, dtype=x.dtype, device=x.device)
        return a.astype(x.dtype, copy=False)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        np.savez(path, mean=self.mean, std=self.std)
        path.with_suffix(".json").write_text(json.dumps({"mean": self.mean.tolist(), "std": self.std.tolist()}))

    @staticmethod
    def load(path: str | Path) -> Normalizer:
        d = np.load(path)
        mean, std = d["mean"].astype(np.float32), d["std"].astype(np.float32)
        if mean.shape != (FRAME_DIM,) or std.shape != (FRAME_DIM,) or not np.all(std > 0):
            raise ValueError(f"{path}: normalization stats must be two ({FRAME_DIM},) arrays with std > 0")
        return Normalizer(mean, std)
