"""Token-by-token decoding for the engine: a static-shape step graph and a Python driver.

Step graph (``DecoderStep``, what gets exported to ONNX), for P components and the causal
decoder's context of K tokens:

    inputs   state  (B, P, K-1) int64   ids of the previous K-1 tokens, oldest first;
                                        before the sequence start: the component's pad id
                                        (= its codebook size, see ``initial_state``)
             tokens (B, P)      int64   the newest token of every component
    outputs  frames (B, F, 335) float32 normalized features of the newest token's F frames
                                        (contact channels as probabilities)
             next_state (B, P, K-1) int64  = window shifted by one (feed back next step)

No position input is needed: the decoder's receptive field is exactly K tokens, so the
window is the whole state, and the step output equals the offline ``ComponentVQ.decode``
of the full sequence (tested to <= 1e-4). A host may equally keep the ring itself and
ignore ``next_state``.
"""

from __future__ import annotations

import torch
from torch import nn

from .vqvae import ComponentVQ


class DecoderStep(nn.Module):
    def __init__(self, vq: ComponentVQ):
        super().__init__()
        if not vq.cfg.causal_decoder:
            raise ValueError("streaming needs the causal decoder (ModelConfig.causal_decoder=True)")
        self.vq = vq
        self.register_buffer(
            "pad_ids", torch.tensor([p.pad_id for p in vq.parts.values()], dtype=torch.long), persistent=False
        )

    @property
    def context_tokens(self) -> int:
        return self.vq.context_tokens

    def initial_state(self, batch_size: int = 1) -> torch.Tensor:
        """(B, P, K-1): every slot is "before the start"."""
        k = self.context_tokens - 1
        return self.pad_ids[None, :, None].expand(batch_size, -1, k).clone()

    def forward(self, state: torch.Tensor, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        window = torch.cat([state, tokens[..., None]], -1)  # (B, P, K)
        frames = torch.cat([part.step_window(window[:, i]) for i, part in enumerate(self.vq.parts.values())], -1)
        return frames, window[..., 1:]


class StreamingDecoder:
    """Keeps the step state between calls: ``step(tokens (B, P)) -> (B, F, 335)``."""

    def __init__(self, vq: ComponentVQ, batch_size: int = 1):
        self.step_fn = DecoderStep(vq)
        self.reset(batch_size)

    def reset(self, batch_size: int = 1) -> None:
        self.state = self.step_fn.initial_state(batch_size)

    @torch.no_grad()
    def step(self, tokens: torch.Tensor) -> torch.Tensor:
        frames, self.state = self.step_fn(self.state, tokens.to(self.state.device))
        return frames
