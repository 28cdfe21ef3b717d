"""Typed configuration of the four coordinated autoregressive Transformers (DESIGN §3).

One dataclass describes every size (paper, small, tiny): the paper model and the
embedded default are the same code with different numbers. The config is saved as
JSON beside checkpoints and its derived ids (End/Pad per stream, L_max) go into the
bundle manifest, so `to_dict`/`from_dict` round-trip exactly and reject unknown keys.

Token ids of stream i: codes 0..J_i-1, End = J_i, Pad = J_i + 1 (vocabulary J_i + 2).
Sequence positions: 0 = condition token (projected text embedding), position p >= 1
holds code p-1; the output at position p predicts code p. block_size = 1 + L_max + 1
(condition + L_max codes + End), so L_max = block_size - 2.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from ..layout import COMPONENTS

STREAMS: tuple[str, ...] = COMPONENTS  # global, body, lhand, rhand: the fixed stream order


@dataclass(frozen=True)
class TransformerConfig:
    codebook_sizes: tuple[int, int, int, int] = (512, 1024, 512, 512)
    widths: tuple[int, int, int, int] = (512, 1024, 768, 768)
    n_layers: int = 14
    n_heads: int = 16
    block_size: int = 76
    d_text: int = 512
    coord_width: int = 256  # common width each stream is projected to before coordination
    coord_hidden: int = 512  # hidden width of the shared 3-layer coordination MLP
    mlp_ratio: int = 4
    dropout: float = 0.1

    def __post_init__(self) -> None:
        object.__setattr__(self, "codebook_sizes", tuple(int(x) for x in self.codebook_sizes))
        object.__setattr__(self, "widths", tuple(int(x) for x in self.widths))
        n = len(STREAMS)
        if len(self.codebook_sizes) != n or len(self.widths) != n:
            raise ValueError(f"need {n} codebook sizes and widths, one per stream {STREAMS}")
        if any(w % self.n_heads for w in self.widths):
            raise ValueError(f"every width {self.widths} must be divisible by n_heads={self.n_heads}")
        if self.n_layers < 1 or self.block_size < 3 or min(self.codebook_sizes) < 1:
            raise ValueError("n_layers >= 1, block_size >= 3 and codebook sizes >= 1 required")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError("dropout must be in [0, 1)")

    # Derived quantities (never stored, so they cannot disagree with the fields).
    @property
    def vocab_sizes(self) -> tuple[int, ...]:
        return tuple(j + 2 for j in self.codebook_sizes)

    @property
    def end_ids(self) -> tuple[int, ...]:
        return tuple(self.codebook_sizes)

    @property
    def pad_ids(self) -> tuple[int, ...]:
        return tuple(j + 1 for j in self.codebook_sizes)

    @property
    def l_max(self) -> int:
        return self.block_size - 2

    @property
    def head_dims(self) -> tuple[int, ...]:
        return tuple(w // self.n_heads for w in self.widths)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["codebook_sizes"] = list(self.codebook_sizes)
        d["widths"] = list(self.widths)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TransformerConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown TransformerConfig keys: {sorted(unknown)}")
        return cls(**d)

    def save_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load_json(cls, path: str | Path) -> TransformerConfig:
        return cls.from_dict(json.loads(Path(path).read_text()))

    def replace(self, **changes) -> TransformerConfig:
        return type(self).from_dict({**self.to_dict(), **changes})


PRESETS: dict[str, TransformerConfig] = {
    # Paper (Sec. IV-A): CLIP text width 512; ~0.45 B parameters.
    "paper": TransformerConfig(),
    # Embedded default on CPU: same architecture, MiniLM text width 384.
    "small": TransformerConfig(
        widths=(128, 256, 192, 192), n_layers=4, n_heads=4, d_text=384,
        coord_width=128, coord_hidden=256,
    ),
    # Unit tests: unequal widths so the coordination projections are exercised.
    "tiny": TransformerConfig(
        codebook_sizes=(16, 32, 16, 24), widths=(32, 48, 32, 32), n_layers=2, n_heads=2,
        block_size=20, d_text=16, coord_width=16, coord_hidden=32, mlp_ratio=2,
    ),
}


def preset(name: str, **overrides) -> TransformerConfig:
    """A named preset with optional field overrides (e.g. d_text=384, codebook sizes)."""
    try:
        base = PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None
    return base.replace(**overrides) if overrides else base
