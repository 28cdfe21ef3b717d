"""EMA-reset vector quantizer (T2M-GPT's ``QuantizeEMAReset``, made checkpoint- and DDP-safe).

The whole state (codebook, EMA sums, EMA counts, the "initialised" flag) is registered
buffers, so ``state_dict`` round trips reproduce codes and EMA statistics exactly and a
resumed run continues where it stopped instead of re-initialising the codebook.

Training-mode forward, per batch of encoder outputs ``x`` (N, d):
1. first batch only: the codebook is drawn from ``x`` (the "init flag");
2. nearest-code assignment;
3. EMA update of per-code sums and counts (decay 0.99); under ``torch.distributed`` the
   batch statistics are all-reduced so every rank applies the same update;
4. codes whose EMA count fell below the dead-code threshold are reset to random encoder
   outputs of the current batch (drawn on rank 0 and broadcast). Unlike T2M-GPT, the reset
   also restarts that code's EMA sum and count, so the next update averages from the new
   vector instead of the stale one.

The threshold is relative by default (``reset_mode="relative"``): a code is dead when its
EMA count of hits per step is below ``reset_threshold`` x the uniform share N/K of the
step's N vectors over K codes. T2M-GPT's absolute threshold (``"absolute"``: below
``reset_threshold`` hits per step) means "below 1/8 of a uniform share" at its 4,096
vectors per step and 512 codes, but "below twice a uniform share" at 128 vectors and 256
codes, where it re-randomises codes in use every step and the codebook never settles
(measured in the tests). Each training step reports how many codes it reset and how many
distinct codes it used, for the training log.
With ``ema_warmup`` (new configs) the EMA is the plain running mean of the steps so far
until that mean's memory reaches the decay's: decay ``min(decay, (n + 1) / (n + 2))`` at
update n, so 0.99 from update 98. Early in training the encoder moves fast and the
codebook drawn from its first batch goes stale; with the full decay from the start only
6-12 codes stay in use until unused ones are found dead 69 steps later, with the warm-up
they are found within a few steps (docs/training.md, "Fitting a small set": a small set
at 65 mm instead of 99 mm at step 50, 30 instead of 60 at step 100). Its update count is a buffer, so a resumed
run continues the same schedule.
The quantized output uses the updated codebook with a straight-through gradient; the
commitment term is ``mse(x, sg[q])`` (weighted by beta in the loss).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn


class Quantized(NamedTuple):
    x_q: torch.Tensor  # (N, d) straight-through quantized vectors
    codes: torch.Tensor  # (N,) int64
    commit: torch.Tensor  # scalar, mse(x, sg[q])
    perplexity: torch.Tensor  # scalar, exp(entropy) of this batch's code histogram
    resets: torch.Tensor  # scalar, codes reset by this (training) step; 0 in eval mode
    used: torch.Tensor  # scalar, distinct codes this batch picked (code usage)


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized()


RESET_MODES = ("relative", "absolute")


class EMAResetQuantizer(nn.Module):
    def __init__(self, codebook_size: int, code_dim: int, decay: float = 0.99, reset_threshold: float = 0.1,
                 reset_mode: str = "relative", ema_warmup: bool = False):
        super().__init__()
        if reset_mode not in RESET_MODES:
            raise ValueError(f"reset_mode must be one of {RESET_MODES}, got {reset_mode!r}")
        self.codebook_size, self.code_dim = codebook_size, code_dim
        self.decay, self.reset_threshold, self.reset_mode = decay, reset_threshold, reset_mode
        self.register_buffer("codebook", torch.zeros(codebook_size, code_dim))
        self.register_buffer("ema_sum", torch.zeros(codebook_size, code_dim))
        self.register_buffer("ema_count", torch.zeros(codebook_size))
        self.register_buffer("initialised", torch.tensor(False))
        # Only with the warm-up, so checkpoints saved before it load unchanged.
        self.ema_warmup = ema_warmup
        if ema_warmup:
            self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))

    def nearest(self, x: torch.Tensor) -> torch.Tensor:
        """(N, d) -> (N,) index of the closest code (squared Euclidean)."""
        c = self.codebook.float()
        x = x.float()
        d2 = x.pow(2).sum(-1, keepdim=True) - 2.0 * x @ c.t() + c.pow(2).sum(-1)[None]
        return d2.argmin(-1)

    def dequantize(self, codes: torch.Tensor) -> torch.Tensor:
        return F.embedding(codes, self.codebook)

    def forward(self, x: torch.Tensor) -> Quantized:
        xd = x.detach().float()
        if self.training and not bool(self.initialised):
            self._initialise(xd)
        codes = self.nearest(xd)
        counts = torch.bincount(codes, minlength=self.codebook_size).float()
        resets = torch.zeros((), device=x.device)
        if self.training:
            counts, resets = self._ema_update(xd, codes, counts)
        q = self.dequantize(codes).to(x.dtype)
        commit = F.mse_loss(x, q.detach())
        p = counts / counts.sum().clamp_min(1.0)
        perplexity = torch.exp(-(p * torch.log(p.clamp_min(1e-10))).sum())
        return Quantized(x + (q - x).detach(), codes, commit, perplexity, resets, (counts > 0).sum().float())

    def dead_threshold(self, n_vectors: torch.Tensor) -> torch.Tensor:
        """EMA hits per step below which a code is reset, for steps of ``n_vectors`` vectors
        (a 0-d tensor, so nothing waits for the device)."""
        if self.reset_mode == "absolute":
            return torch.full_like(n_vectors, self.reset_threshold)
        return self.reset_threshold * n_vectors / self.codebook_size

    def _restart_count(self, threshold: torch.Tensor) -> torch.Tensor:
        """EMA count a new or reset code starts from. Relative mode: twice the threshold, so
        a code nobody picks is found dead after ln 2 / (1 - decay) steps (69 at 0.99) rather
        than after hundreds; absolute mode: T2M-GPT's (1 at init, the threshold at a reset)."""
        return (2.0 * threshold).clamp_min(1e-3) if self.reset_mode == "relative" else threshold.clamp_min(1e-3)

    @torch.no_grad()
    def _initialise(self, x: torch.Tensor) -> None:
        rows = self._broadcast(self._sample_rows(x, self.codebook_size))
        n = torch.tensor(float(x.shape[0]), device=x.device)
        if _distributed():
            dist.all_reduce(n)
        count = self._restart_count(self.dead_threshold(n)) if self.reset_mode == "relative" else torch.ones_like(n)
        self.codebook.copy_(rows)
        self.ema_sum.copy_(rows * count)
        self.ema_count.fill_(float(count))
        self.initialised.fill_(True)

    @torch.no_grad()
    def _ema_update(self, x: torch.Tensor, codes: torch.Tensor, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns the (all-reduced) batch code counts and the number of codes reset."""
        sums = torch.zeros_like(self.ema_sum).index_add_(0, codes, x)
        if _distributed():
            dist.all_reduce(sums)
            dist.all_reduce(counts)
        if self.ema_warmup:
            decay = self._warmup_decay()
            self.ema_sum.mul_(decay).add_(sums * (1.0 - decay))
            self.ema_count.mul_(decay).add_(counts * (1.0 - decay))
        else:
            self.ema_sum.mul_(self.decay).add_(sums, alpha=1.0 - self.decay)
            self.ema_count.mul_(self.decay).add_(counts, alpha=1.0 - self.decay)
        threshold = self.dead_threshold(counts.sum())
        dead = self.ema_count < threshold
        fresh = self._broadcast(self._sample_rows(x, self.codebook_size))
        restart = self._restart_count(threshold)
        self.ema_sum.copy_(torch.where(dead[:, None], fresh * restart, self.ema_sum))
        self.ema_count.copy_(torch.where(dead, restart.expand_as(self.ema_count), self.ema_count))
        self.codebook.copy_(self.ema_sum / self.ema_count[:, None])
        return counts, dead.sum().float()

    def _warmup_decay(self) -> torch.Tensor:
        """This update's decay under the warm-up (module doc), a 0-d tensor so nothing
        waits for the device."""
        n = self.ema_updates.to(torch.float32)
        self.ema_updates.add_(1)
        return torch.clamp((n + 1.0) / (n + 2.0), max=self.decay)

    @staticmethod
    def _sample_rows(x: torch.Tensor, n: int) -> torch.Tensor:
        """``n`` random rows of ``x``; tiled with small noise when the batch has fewer rows."""
        if x.shape[0] < n:
            reps = math.ceil(n / x.shape[0])
            x = x.repeat(reps, 1)
            x = x + torch.randn_like(x) * (0.01 / math.sqrt(x.shape[1]))
        return x[torch.randperm(x.shape[0], device=x.device)[:n]]

    @staticmethod
    def _broadcast(t: torch.Tensor) -> torch.Tensor:
        """Rank 0's draw for every rank, so the codebooks never diverge."""
        if _distributed():
            t = t.contiguous()
            dist.broadcast(t, 0)
        return t
