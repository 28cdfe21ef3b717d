"""Reference token sampler, bit-exact contract with the Rust engine (DESIGN §4).

Everything here uses only IEEE-754 float64 +, -, *, /, floor and comparisons (each
correctly rounded, no fused multiply-add) plus 64-bit integer arithmetic, so any
language reproduces it bit for bit. Even `exp` is our own (`exp_det`) because libm
`exp` differs by an ulp between platforms (glibc, MSVC, macOS).

Random numbers: one SplitMix64 generator per sequence, state = seed mod 2^64:

    next_u64: state += 0x9E3779B97F4A7C15; z = state
              z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9
              z = (z ^ (z >> 27)) * 0x94D049BB133111EB
              return z ^ (z >> 31)                          (all mod 2^64)
    uniform:  u = float64(next_u64 >> 11) * 2^-53           (u in [0, 1))

Batched generation with one integer seed gives element b the seed (seed + b) mod 2^64,
so element b of a batch draws exactly what a single-sequence run with that seed draws.

Per decode step k (k = index of the code being produced, k = 0 is the step whose input
is the condition token) draw exactly four uniforms, u_global, u_body, u_lhand, u_rhand
in that order, ALWAYS (also when greedy), so a seed's stream stays aligned whatever
the parameters. Then for each stream, with logits x (float32, length V = J + 2,
End = J, Pad = J + 1), independently:

 1. allowed = every id except Pad; if k < min_len: End is not allowed;
    if k >= max_len: only End is allowed. All logits must be finite (else error).
 2. Greedy (temperature == 0): the allowed id with the largest float64(x), lowest id
    on ties. Done (top_k ignored).
 3. z_i = float64(x_i) / temperature for allowed i (temperature >= 1e-4).
 4. Top-k (0 < top_k < number of allowed ids): keep the top_k allowed ids ranked by
    z descending, ties broken by lower id first. Otherwise keep all allowed ids.
 5. m = max z over kept ids; w_i = exp_det(z_i - m) for kept ids, w_i = 0 otherwise.
 6. c_i = c_{i-1} + w_i sequentially in id order (c_{-1} = 0); total = c_{V-1}.
 7. token = the first id i with c_i > u * total. If rounding leaves none (possible
    only when u * total rounds up to total), the largest id with w_i > 0.

exp_det(d) for d <= 0 (d = z - m):
    if d < -700: return 0.0
    k = floor(d * INV_LN2 + 0.5)
    r = (d - k * LN2_HI) - k * LN2_LO
    p = EXP_COEFFS[13]; for n = 12 down to 0: p = p * r + EXP_COEFFS[n]   (no FMA)
    return p * 2^k       (2^k built exactly from the exponent bits; k in [-1010, 0])
with the constants below (repr round-trips, so Rust float literals give the same bits).
exp_det(0) == 1.0 exactly, so total >= 1. Relative error vs exp is ~1e-16.

Classifier-free guidance (`SamplingParams.guidance` = s, s != 1): every step also runs the
model on the null condition (a zero text embedding, what `train-gpt --text-dropout` trains
on) with its own cache and the same tokens, and the logits handed to rule 1 are, per
element in float32, u + s32 * (c - u) (c: with the text, u: null, s32: s rounded to
float32; each operation rounded, no fused multiply-add). s = 1 is the text alone: one pass.

Sequence end (in `generate`): all four streams share one length; generation stops for
a sequence at the first step k where any stream samples End; its length is k (the
codes of steps 0..k-1) and the other streams' tokens of step k are discarded. At
k = max_len End is forced in all streams, so the length is at most max_len <= L_max.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch

from .gpt_configs import TransformerConfig

_M64 = (1 << 64) - 1
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)

INV_LN2 = 1.4426950408889634
LN2_HI = 0.6931471803691238  # fdlibm ln2_hi: low 32 bits zero, so k * LN2_HI is exact
LN2_LO = 1.9082149292705877e-10
EXP_COEFFS = (  # 1/n!, n = 0..13, each the float64 nearest to it
    1.0, 1.0, 0.5, 0.16666666666666666, 0.041666666666666664, 0.008333333333333333,
    0.001388888888888889, 0.0001984126984126984, 2.48015873015873e-05,
    2.7557319223985893e-06, 2.755731922398589e-07, 2.505210838544172e-08,
    2.08767569878681e-09, 1.6059043836821613e-10,
)
EXP_UNDERFLOW = -700.0
MIN_TEMPERATURE = 1e-4


class SplitMix64:
    """One SplitMix64 generator per batch element, advanced together (vectorised)."""

    def __init__(self, seeds: Sequence[int] | int):
        seeds = [int(s) & _M64 for s in np.atleast_1d(np.asarray(seeds, dtype=object))]
        self.state = np.array(seeds, dtype=np.uint64)

    def next_u64(self) -> np.ndarray:
        with np.errstate(over="ignore"):
            self.state = self.state + _GOLDEN
            z = self.state
            z = (z ^ (z >> np.uint64(30))) * _MIX1
            z = (z ^ (z >> np.uint64(27))) * _MIX2
            return z ^ (z >> np.uint64(31))

    def next_uniform(self) -> np.ndarray:
        """float64 in [0, 1): the top 53 bits times 2^-53 (both steps exact)."""
        return (self.next_u64() >> np.uint64(11)).astype(np.float64) * (2.0 ** -53)


def resolve_seeds(seed: int | Sequence[int], batch: int) -> list[int]:
    """One seed per batch element: an int gives (seed + b) mod 2^64."""
    if isinstance(seed, (int, np.integer)):
        return [(int(seed) + b) & _M64 for b in range(batch)]
    seeds = [int(s) & _M64 for s in seed]
    if len(seeds) != batch:
        raise ValueError(f"{len(seeds)} seeds for a batch of {batch}")
    return seeds


def exp_det(d: np.ndarray) -> np.ndarray:
    """Deterministic exp for d <= 0 (see module docstring); elementwise, float64."""
    d = np.asarray(d, dtype=np.float64)
    under = d < EXP_UNDERFLOW
    d = np.where(under, 0.0, d)
    k = np.floor(d * INV_LN2 + 0.5)
    r = (d - k * LN2_HI) - k * LN2_LO
    p = np.full_like(r, EXP_COEFFS[-1])
    for c in EXP_COEFFS[-2::-1]:
        p = p * r + c
    return np.where(under, 0.0, np.ldexp(p, k.astype(np.int32)))


@dataclass(frozen=True)
class SamplingParams:
    """temperature 0 = greedy; top_k 0 = off; End forbidden at steps k < min_len and
    forced at k == max_len (None = the model's L_max); guidance: the classifier-free
    guidance scale (module docstring), 1 = off. Serialized into the manifest."""

    temperature: float = 1.0
    top_k: int = 0
    min_len: int = 0
    max_len: int | None = None
    guidance: float = 1.0

    def __post_init__(self) -> None:
        t = float(self.temperature)
        if not (t == 0.0 or MIN_TEMPERATURE <= t < float("inf")):
            raise ValueError(f"temperature must be 0 or >= {MIN_TEMPERATURE}, got {t}")
        g = float(self.guidance)
        if not (0.0 <= g <= float(np.finfo(np.float32).max)):  # finite in float32 (NaN fails too)
            raise ValueError(f"guidance must be finite and >= 0, got {g}")
        if self.top_k < 0 or self.min_len < 0 or (self.max_len is not None and self.max_len < 0):
            raise ValueError("top_k, min_len and max_len must be >= 0")

    def resolved_max_len(self, l_max: int) -> int:
        max_len = l_max if self.max_len is None else self.max_len
        if not self.min_len <= max_len <= l_max:
            raise ValueError(f"need min_len {self.min_len} <= max_len {max_len} <= L_max {l_max}")
        return max_len

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> SamplingParams:
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown SamplingParams keys: {sorted(unknown)}")
        return cls(**d)


def allowed_ids(vocab: int, end_id: int, pad_id: int, k: int, min_len: int, max_len: int) -> np.ndarray:
    """Rule 1 of the module docstring: (V,) bool."""
    allowed = np.ones(vocab, dtype=bool)
    allowed[pad_id] = False
    if k >= max_len:
        allowed[:] = False
        allowed[end_id] = True
    elif k < min_len:
        allowed[end_id] = False
    return allowed


def sample_logits(logits: np.ndarray, u: np.ndarray, allowed: np.ndarray,
                  temperature: float, top_k: int) -> np.ndarray:
    """Rules 2-7 for a batch: logits (B, V) float32, u (B,) float64 -> ids (B,) int64."""
    x = np.asarray(logits, dtype=np.float32).astype(np.float64)
    if not np.isfinite(x).all():
        raise ValueError("non-finite logits")
    if temperature == 0.0:
        return np.argmax(np.where(allowed, x, -np.inf), axis=1)  # first max = lowest id
    z = np.where(allowed, x / temperature, -np.inf)
    keep = np.broadcast_to(allowed, z.shape)
    if 0 < top_k < int(allowed.sum()):
        order = np.argsort(-z, axis=1, kind="stable")  # stable: equal z keep id order
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.broadcast_to(np.arange(z.shape[1]), z.shape), axis=1)
        keep = keep & (rank < top_k)
    m = np.max(np.where(keep, z, -np.inf), axis=1, keepdims=True)
    w = np.where(keep, exp_det(np.where(keep, z - m, 0.0)), 0.0)
    c = np.cumsum(w, axis=1)  # add.accumulate: strictly sequential in id order
    above = c > (np.asarray(u, dtype=np.float64) * c[:, -1])[:, None]
    last_positive = w.shape[1] - 1 - np.argmax(w[:, ::-1] > 0, axis=1)
    return np.where(above.any(axis=1), np.argmax(above, axis=1), last_positive)


class TokenSampler:
    """Samples the four streams of one step for B sequences with per-sequence RNGs."""

    def __init__(self, cfg: TransformerConfig, params: SamplingParams, seeds: Sequence[int]):
        self.cfg, self.params = cfg, params
        self.max_len = params.resolved_max_len(cfg.l_max)
        self.rng = SplitMix64(seeds)

    def sample(self, logits: Sequence[np.ndarray], k: int) -> np.ndarray:
        """logits: per stream (B, V_i) float32; k: step index -> tokens (B, 4) int64."""
        us = [self.rng.next_uniform() for _ in logits]  # global, body, lhand, rhand
        cfg, p = self.cfg, self.params
        return np.stack([
            sample_logits(lg, u, allowed_ids(v, e, pad, k, p.min_len, self.max_len),
                          p.temperature, p.top_k)
            for lg, u, v, e, pad in zip(logits, us, cfg.vocab_sizes, cfg.end_ids, cfg.pad_ids)
        ], axis=1).astype(np.int64)


@dataclass
class Generation:
    """tokens (B, L, 4) int64: codes per stream, Pad after each sequence's length;
    lengths (B,) int64: number of codes (End excluded)."""

    tokens: torch.Tensor
    lengths: torch.Tensor

    def stream(self, i: int) -> torch.Tensor:
        return self.tokens[..., i]


StepFn = Callable[[np.ndarray, int], Sequence[np.ndarray]]


def run_sampling_loop(step_fn: StepFn, cfg: TransformerConfig, batch: int,
                      params: SamplingParams, seeds: Sequence[int]) -> Generation:
    """The decode loop shared by every backend (PyTorch with/without cache, ONNX).

    step_fn(tokens (B, 4) int64 = codes of step k-1 (Pad ids at k = 0), k) returns the
    logits of step k per stream as float32 (B, V_i) arrays.
    """
    sampler = TokenSampler(cfg, params, seeds)
    end = np.array(cfg.end_ids)
    pad = np.array(cfg.pad_ids, dtype=np.int64)
    tokens = np.broadcast_to(pad, (batch, len(end))).copy()
    lengths = np.full(batch, -1, dtype=np.int64)
    history = []
    for k in range(sampler.max_len + 1):
        tokens = sampler.sample(step_fn(tokens, k), k)
        ended = (tokens == end).any(axis=1) & (lengths < 0)
        lengths[ended] = k
        history.append(tokens)
        if (lengths >= 0).all():
            break
    seq = np.stack(history, axis=1)[:, : int(lengths.max())]
    seq = np.where(np.arange(seq.shape[1])[None, :, None] < lengths[:, None, None], seq, pad)
    return Generation(torch.from_numpy(np.ascontiguousarray(seq)), torch.from_numpy(lengths))


def guide_logits(cond: np.ndarray, uncond: np.ndarray, scale: float) -> np.ndarray:
    """Classifier-free guidance, float32 elementwise: uncond + scale * (cond - uncond)."""
    c, u = np.asarray(cond, dtype=np.float32), np.asarray(uncond, dtype=np.float32)
    return u + np.float32(scale) * (c - u)


@torch.no_grad()
def generate(model, text_emb: torch.Tensor, params: SamplingParams = SamplingParams(),
             seed: int | Sequence[int] = 0, use_cache: bool = True) -> Generation:
    """Batched generation from text embeddings (B, d_text) on the model's device.

    use_cache=False re-runs the full forward pass over the prefix at every step (the
    benchmark's no-cache reference); both paths feed the same sampler and loop.
    """
    cfg = model.cfg
    batch, device = text_emb.shape[0], text_emb.device
    guidance = params.guidance
    guided = guidance != 1.0
    if guided:  # elements B..2B-1: the same sequences on the null condition
        text_emb = torch.cat([text_emb, torch.zeros_like(text_emb)])
    rows = text_emb.shape[0]
    was_training = model.training
    model.eval()
    cache = model.new_cache(rows) if use_cache else None
    prefix: list[torch.Tensor] = []

    def to_np(logits):
        out = [lg.float().cpu().numpy() for lg in logits]
        return [guide_logits(lg[:batch], lg[batch:], guidance) for lg in out] if guided else out

    def step_fn(tokens: np.ndarray, k: int):
        t = torch.from_numpy(np.concatenate([tokens, tokens]) if guided else tokens).to(device)
        if use_cache:
            return to_np(model.decode_step(t, k, text_emb, cache))
        if k > 0:
            prefix.append(t)
        seq = torch.stack(prefix, 1) if prefix else t.new_zeros((rows, 0, t.shape[1]))
        return to_np(lg[:, -1] for lg in model(text_emb, seq))

    try:
        return run_sampling_loop(step_fn, cfg, batch, params, resolve_seeds(seed, batch))
    finally:
        model.train(was_training)
