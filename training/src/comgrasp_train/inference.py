"""Text -> motion with trained PyTorch models (the reference the engine is compared to).

A :class:`MotionModel` holds the VQ, the Transformer, the text encoder and the
normalization statistics of one training run; ``generate`` returns de-normalized 335-D
frames per prompt, decoded from the sampled tokens by the (causal) VQ decoder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .models.sampling import SamplingParams, generate
from .normalization import Normalizer
from .text_encoder import load_text_encoder
from .train.gpt_trainer import load_gpt
from .train.vq_trainer import load_vq


@dataclass
class MotionModel:
    vq: torch.nn.Module
    gpt: torch.nn.Module
    encoder: object
    normalizer: Normalizer
    fps: float
    device: torch.device
    checkpoints: tuple[dict, dict] = ({}, {})  # which file and step of the VQ and GPT runs

    @staticmethod
    def load(vq_dir: Path, gpt_dir: Path, device: str = "cpu", text_weights: str | None = None) -> MotionModel:
        """The models of a VQ run and a GPT run; the text encoder as the GPT run's config
        names it (its weight scheme: "fp32" | "int8" | "int8-tok4", unless ``text_weights``
        overrides it)."""
        vq, _, vq_conf = load_vq(vq_dir, device)
        gpt, _, gpt_conf = load_gpt(gpt_dir, device)
        text = gpt_conf["text"]
        enc = load_text_encoder(text["backend"], checkpoint=text.get("checkpoint"), max_tokens=text.get("max_tokens"),
                                weights=text_weights or text.get("weights", "fp32"))
        norm = Normalizer.load(Path(vq_dir) / "stats.npz")
        return MotionModel(vq, gpt, enc, norm, float(vq_conf["fps"]), torch.device(device),
                           (vq_conf["checkpoint"], gpt_conf["checkpoint"]))

    @torch.no_grad()
    def decode(self, tokens: torch.Tensor, length: int) -> np.ndarray:
        """(L, 4) codes -> (L * 16, 335) de-normalized frames."""
        x = self.vq.decode(tokens[:length].T[None].to(self.device))[0]
        return self.normalizer.denormalize(x.cpu().numpy().astype(np.float32))

    @torch.no_grad()
    def generate(self, texts: list[str], params: SamplingParams = SamplingParams(), seed: int = 0) -> list[np.ndarray]:
        emb = self.encoder.encode(texts).to(self.device)
        out = generate(self.gpt, emb, params, seed)
        return [self.decode(out.tokens[b], int(out.lengths[b])) for b in range(len(texts))]
