"""Four coordinated autoregressive Transformers (ComGrasp, Sec. III-D; DESIGN §3).

One GPT per component stream (global, body, lhand, rhand), each with its own width,
all with the same depth. Position 0 of every stream is the condition token (the text
embedding through a per-stream linear projection); position p >= 1 holds code p-1 and
the output at position p predicts code p. Before every layer except the first the
streams exchange information at the same time step (part coordination):

    h_i <- LayerNorm_i(h_i + out_i(MLP(concat_{j != i} in_j(h_j))))

with per-stream input projections in_j to a common width, ONE shared 3-layer MLP (the
three other streams concatenated in global, body, lhand, rhand order) and per-stream
output projections out_i. Coordination is per time step, so causality is kept.

Two execution paths share every weight and every layer's code (`_trunk`):

* `forward(text_emb, tokens)`: teacher-forced full sequence (training, no-cache decoding).
* `step(tokens, pos, text_emb, cache_k, cache_v)`: one decode step of all four streams
  against a FIXED-size cache of `block_size` slots per layer. The step reads the cache
  (slots < pos are valid, the rest are masked) and returns only the new position's
  k/v rows; the caller owns the cache and writes row `pos`. This is exactly the graph
  exported to ONNX for the Rust engine (static shapes, no scatter: the new k/v enter the
  attention as a separate 77th score instead of being written into the cache).
  At pos == 0 the step uses the condition projection instead of the token embedding,
  so one graph serves the condition step and the token steps.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .gpt_configs import TransformerConfig

_MASKED = -1.0e30  # finite "minus infinity": exp underflows to exactly 0, no inf-inf NaNs


def cached_attention(q: Tensor, k: Tensor, v: Tensor, cache_k: Tensor, cache_v: Tensor,
                     valid: Tensor, scale: float) -> Tensor:
    """Attention of one new position over a fixed cache plus itself.

    q, k, v: (B, H, 1, D) of the new position; cache_k/cache_v: (B, H, S, D) with slots
    < pos filled; valid: (S,) bool, True for slots < pos. Equivalent to writing (k, v)
    into slot pos and masking slots > pos, but needs no scatter and leaves the cache
    read-only (the caller writes the row afterwards). Unfilled slots must be finite.
    scale = 1/sqrt(D) as a Python float (a constant in the exported graph).
    """
    s_cache = torch.matmul(q, cache_k.transpose(-1, -2)) * scale  # (B, H, 1, S)
    s_cache = s_cache.masked_fill(~valid, _MASKED)
    s_new = torch.matmul(q, k.transpose(-1, -2)) * scale  # (B, H, 1, 1); MatMul, no ReduceSum
    p = torch.softmax(torch.cat([s_cache, s_new], dim=-1), dim=-1)
    n_slots = cache_k.shape[-2]
    return torch.matmul(p[..., :n_slots], cache_v) + p[..., n_slots:] * v


class CausalSelfAttention(nn.Module):
    def __init__(self, width: int, n_heads: int, dropout: float):
        super().__init__()
        self.width, self.n_heads, self.head_dim = width, n_heads, width // n_heads
        self.scale = 1.0 / math.sqrt(self.head_dim)
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)
        self.attn_dropout = dropout
        self.resid_drop = nn.Dropout(dropout)

    def forward(self, x: Tensor, cache: tuple[Tensor, Tensor, Tensor] | None = None
                ) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        """x (B, T, W) -> (y (B, T, W), (k, v) each (B, H, T, D)). With `cache`
        (cache_k, cache_v, valid), T must be 1 and attention is `cached_attention`."""
        b, t, _ = x.shape
        q, k, v = (z.reshape(b, t, self.n_heads, self.head_dim).transpose(1, 2)
                   for z in self.qkv(x).split(self.width, dim=-1))
        if cache is None:
            p = self.attn_dropout if self.training else 0.0
            y = F.scaled_dot_product_attention(q, k, v, dropout_p=p, is_causal=True)
        else:
            y = cached_attention(q, k, v, *cache, scale=self.scale)
        y = y.transpose(1, 2).reshape(b, t, self.width)
        return self.resid_drop(self.proj(y)), (k, v)


class Block(nn.Module):
    """Pre-LN Transformer block (nanoGPT)."""

    def __init__(self, width: int, n_heads: int, mlp_ratio: int, dropout: float):
        super().__init__()
        self.ln1 = nn.LayerNorm(width)
        self.attn = CausalSelfAttention(width, n_heads, dropout)
        self.ln2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(
            nn.Linear(width, mlp_ratio * width), nn.GELU(),
            nn.Linear(mlp_ratio * width, width), nn.Dropout(dropout),
        )

    def forward(self, x: Tensor, cache=None) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        a, kv = self.attn(self.ln1(x), cache)
        x = x + a
        return x + self.mlp(self.ln2(x)), kv


class PartCoordination(nn.Module):
    """h_i <- LN_i(h_i + out_i(MLP(concat_{j != i} in_j(h_j)))), MLP shared by all i.

    The four target streams go through the shared MLP in one call (stacked on a new
    leading axis), so the cost is one batched MLP, not four Python-level passes.
    """

    def __init__(self, widths: tuple[int, ...], coord_width: int, hidden: int, dropout: float):
        super().__init__()
        n = len(widths)
        self.inp = nn.ModuleList(nn.Linear(w, coord_width) for w in widths)
        self.mlp = nn.Sequential(
            nn.Linear((n - 1) * coord_width, hidden), nn.GELU(),
            nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, coord_width),
        )
        self.out = nn.ModuleList(nn.Linear(coord_width, w) for w in widths)
        self.norm = nn.ModuleList(nn.LayerNorm(w) for w in widths)
        self.drop = nn.Dropout(dropout)
        self.others = [[j for j in range(n) if j != i] for i in range(n)]

    def forward(self, hs: list[Tensor]) -> list[Tensor]:
        p = [f(h) for f, h in zip(self.inp, hs)]
        m = self.mlp(torch.stack([torch.cat([p[j] for j in js], dim=-1) for js in self.others]))
        return [ln(h + self.drop(out(m[i])))
                for i, (h, out, ln) in enumerate(zip(hs, self.out, self.norm))]


class StreamGPT(nn.Module):
    """Embeddings, blocks and head of one stream (its blocks run inside `_trunk`)."""

    def __init__(self, cfg: TransformerConfig, i: int):
        super().__init__()
        w, v = cfg.widths[i], cfg.vocab_sizes[i]
        self.cond = nn.Linear(cfg.d_text, w)  # text embedding -> condition token (position 0)
        self.tok = nn.Embedding(v, w)
        self.pos = nn.Parameter(torch.zeros(cfg.block_size, w))
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(
            Block(w, cfg.n_heads, cfg.mlp_ratio, cfg.dropout) for _ in range(cfg.n_layers))
        self.ln_f = nn.LayerNorm(w)
        self.head = nn.Linear(w, v, bias=False)


class KVCache:
    """Fixed-size cache owned by the caller: per stream k and v of shape
    (n_layers, B, n_heads, block_size, head_dim), zero-initialized (finite)."""

    def __init__(self, cfg: TransformerConfig, batch: int, device=None, dtype=torch.float32):
        shapes = [(cfg.n_layers, batch, cfg.n_heads, cfg.block_size, d) for d in cfg.head_dims]
        self.k = [torch.zeros(s, device=device, dtype=dtype) for s in shapes]
        self.v = [torch.zeros(s, device=device, dtype=dtype) for s in shapes]

    def write(self, pos: int, new_k: list[Tensor], new_v: list[Tensor]) -> None:
        """Store the rows returned by `step` (each (n_layers, B, H, 1, D)) at slot pos."""
        for c, n in zip(self.k + self.v, list(new_k) + list(new_v)):
            c[:, :, :, pos:pos + 1] = n


class ComGraspTransformer(nn.Module):
    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        self.cfg = cfg
        self.streams = nn.ModuleList(StreamGPT(cfg, i) for i in range(len(cfg.widths)))
        self.coord = nn.ModuleList(
            PartCoordination(cfg.widths, cfg.coord_width, cfg.coord_hidden, cfg.dropout)
            for _ in range(cfg.n_layers - 1))
        self.register_buffer("slots", torch.arange(cfg.block_size), persistent=False)
        self.apply(self._init_weights)
        for name, p in self.named_parameters():  # GPT-2 scaled init of residual projections
            if name.endswith("attn.proj.weight") or name.endswith("mlp.2.weight"):
                nn.init.normal_(p, 0.0, 0.02 / math.sqrt(2 * cfg.n_layers))

    @staticmethod
    def _init_weights(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, 0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Embedding):
            nn.init.normal_(m.weight, 0.0, 0.02)
        elif isinstance(m, StreamGPT):
            nn.init.normal_(m.pos, 0.0, 0.02)

    def _trunk(self, hs: list[Tensor], caches=None):
        """Blocks + coordination + heads. caches[i][l] = (cache_k, cache_v, valid) or None.
        Returns (logits per stream, [[(k, v) per layer] per stream])."""
        kvs: list[list] = [[] for _ in hs]
        for layer in range(self.cfg.n_layers):
            if layer > 0:
                hs = self.coord[layer - 1](hs)
            for i, s in enumerate(self.streams):
                hs[i], kv = s.blocks[layer](hs[i], None if caches is None else caches[i][layer])
                kvs[i].append(kv)
        return [s.head(s.ln_f(h)) for s, h in zip(self.streams, hs)], kvs

    def forward(self, text_emb: Tensor, tokens: Tensor) -> list[Tensor]:
        """text_emb (B, d_text), tokens (B, T, 4) with T <= block_size - 1 ->
        logits per stream (B, T + 1, V_i); output p predicts code p."""
        t = tokens.shape[1] + 1
        if t > self.cfg.block_size:
            raise ValueError(f"sequence of {t} positions exceeds block_size {self.cfg.block_size}")
        hs = []
        for i, s in enumerate(self.streams):
            x = torch.cat([s.cond(text_emb)[:, None], s.tok(tokens[..., i])], dim=1) + s.pos[:t]
            hs.append(s.drop(x))
        return self._trunk(hs)[0]

    def loss(self, text_emb: Tensor, codes: Tensor) -> tuple[Tensor, list[Tensor]]:
        """Summed (over streams) mean NLL. codes (B, T, 4): codes, then End, then Pad
        (Pad targets ignored); T <= block_size - 1. Inputs are codes[:, :-1]."""
        return stream_nll(self(text_emb, codes[:, :-1]), codes, self.cfg.pad_ids)

    def step(self, tokens: Tensor, pos: Tensor | int, text_emb: Tensor,
             cache_k: list[Tensor], cache_v: list[Tensor]):
        """One decode step of all four streams.

        tokens (B, 4) int64: codes at position pos (ignored at pos 0, but must be valid
        ids, e.g. Pad); pos: int64 (1,) or int, shared by the batch; text_emb (B, d_text);
        cache_k/cache_v: per stream (n_layers, B, H, block_size, D), slots < pos filled.
        Returns (logits per stream (B, V_i), new_k per stream, new_v per stream), the new
        rows being (n_layers, B, H, 1, D) for slot pos.
        """
        if not isinstance(pos, Tensor):  # never re-wrap a tensor: the tracer would freeze it
            pos = torch.tensor([pos], dtype=torch.long, device=self.slots.device)
        pos = pos.reshape(1)
        valid = self.slots < pos
        is_cond = (pos == 0)[:, None]  # (1, 1): condition step selects the text projection
        hs = [(torch.where(is_cond, s.cond(text_emb), s.tok(tokens[:, i])) + s.pos[pos])[:, None]
              for i, s in enumerate(self.streams)]
        caches = [[(ck[layer], cv[layer], valid) for layer in range(self.cfg.n_layers)]
                  for ck, cv in zip(cache_k, cache_v)]
        logits, kvs = self._trunk(hs, caches)
        new_k = [torch.stack([k for k, _ in kv]) for kv in kvs]
        new_v = [torch.stack([v for _, v in kv]) for kv in kvs]
        return [lg[:, 0] for lg in logits], new_k, new_v

    def new_cache(self, batch: int) -> KVCache:
        p = self.slots
        return KVCache(self.cfg, batch, device=p.device, dtype=self.streams[0].pos.dtype)

    def decode_step(self, tokens: Tensor, pos: int, text_emb: Tensor, cache: KVCache) -> list[Tensor]:
        """`step` plus writing the new rows into `cache` (the PyTorch-side bookkeeping)."""
        logits, new_k, new_v = self.step(tokens, pos, text_emb, cache.k, cache.v)
        cache.write(pos, new_k, new_v)
        return logits


def stream_nll(logits: list[Tensor], codes: Tensor, pad_ids) -> tuple[Tensor, list[Tensor]]:
    """Summed per-stream mean NLL of targets ``codes`` (B, T, 4); Pad targets ignored."""
    per = [F.cross_entropy(lg.flatten(0, 1), codes[..., i].flatten(), ignore_index=pad)
           for i, (lg, pad) in enumerate(zip(logits, pad_ids))]
    return torch.stack(per).sum(), per


def count_parameters(cfg: TransformerConfig) -> int:
    """Parameter count without allocating weights (meta device)."""
    with torch.device("meta"):
        return sum(p.numel() for p in ComGraspTransformer(cfg).parameters())
