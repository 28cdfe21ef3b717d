"""Typed configs of the component VQ-VAEs, their presets, and JSON (de)serialisation.

Presets (codebook size x code dim per component; Table III of the paper gives "default"):

=========  ===========  ============  ============  =====================================
preset     global       body          each hand     note
=========  ===========  ============  ============  =====================================
tiny       32 x 16      32 x 16       32 x 16       tests / CPU smoke runs only
small      256 x 64     512 x 128     256 x 96      our choice: half the codes and dims
default    512 x 128    1024 x 256    512 x 192     paper, Table III
big        1024 x 256   2048 x 512    1024 x 384    our choice: double the codes and dims
=========  ===========  ============  ============  =====================================

The conv width of each component (global 256, body 512, hands 384) is the same in small,
default and big, so the presets ablate the codebook only, as Table III does.

The config is saved beside every checkpoint as JSON (``to_dict`` / ``from_dict``), so a
checkpoint can be rebuilt without the code's defaults (which may change).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from ..layout import COMPONENT_SLICES, COMPONENTS, CONTACT_CHANNELS, FRAME_DIM

SINGLE = "all"  # the component name of the single-VQ-VAE ablation (all 335 features)


@dataclass(frozen=True)
class ComponentConfig:
    """One tokenizer: which features it reads, its codebook, its conv width."""

    name: str  # "global" | "body" | "lhand" | "rhand" | "all"
    codebook_size: int
    code_dim: int
    width: int

    @property
    def feature_slice(self) -> slice:
        return slice(0, FRAME_DIM) if self.name == SINGLE else COMPONENT_SLICES[self.name]

    @property
    def dim(self) -> int:
        s = self.feature_slice
        return s.stop - s.start

    @property
    def contact_channels(self) -> tuple[int, ...]:
        """Contact channels as indices into this component's own slice."""
        s = self.feature_slice
        return tuple(c - s.start for c in CONTACT_CHANNELS if s.start <= c < s.stop)


@dataclass(frozen=True)
class ModelConfig:
    """Architecture shared by all components (only codebooks and widths differ)."""

    components: tuple[ComponentConfig, ...]
    down_t: int = 4  # 2**down_t frames per token
    # Encoder (non-causal; tokens come from the Transformer at inference): T2M-GPT-style
    # conv stack plus cross-frame self-attention at the token rate.
    res_depth: int = 3  # residual blocks per level (encoder and non-causal decoder)
    dilation_growth: int = 3
    enc_attn_layers: int = 1
    attn_heads: int = 4
    # Decoder. causal=True is our streaming decoder (DESIGN deviation 1); False is the
    # paper's decoder, which sees the whole token sequence.
    causal_decoder: bool = True
    causal_kernel: int = 2  # conv kernel of the causal decoder (keeps the receptive field small)
    causal_depth: int = 1  # residual blocks per level of the causal decoder
    dec_attn_window: int = 4  # causal local attention over this many tokens; 0 = none
    # Quantizer
    ema_decay: float = 0.99
    # Dead codes are reset; "relative": EMA hits per step < reset_threshold x N/K (N vectors
    # per step, K codes); "absolute" (T2M-GPT, checkpoints saved before the switch): < reset_threshold.
    reset_threshold: float = 0.1
    reset_mode: str = "relative"
    # The EMA starts as a running mean (models.quantizer); configs saved before: off.
    ema_warmup: bool = True

    def __post_init__(self):
        if self.down_t < 1:
            raise ValueError("down_t must be >= 1")
        names = [c.name for c in self.components]
        if names not in (list(COMPONENTS), [SINGLE]):
            raise ValueError(f"components must be {list(COMPONENTS)} or [{SINGLE!r}], got {names}")
        for c in self.components:
            if c.width % self.attn_heads:
                raise ValueError(f"{c.name}: width {c.width} is not divisible by attn_heads {self.attn_heads}")

    @property
    def frames_per_token(self) -> int:
        return 2**self.down_t

    @property
    def single(self) -> bool:
        return self.components[0].name == SINGLE


@dataclass(frozen=True)
class LossConfig:
    """VQ-VAE objective (paper Sec. IV-A)."""

    beta: float = 0.05  # commitment
    lambda_joint: float = 1.0
    # Hands' orientation in metres (models.vq_losses.hand_axes): the turn of a held object.
    # Off by default: at 10 it tripled the reconstructed pours that pass the checker but
    # cost the body 4.6 mm and other intents as many passes (docs/training.md).
    lambda_hand: float = 0.0
    # "all" frames, or only the frames where that hand holds the object (its contact label):
    # where the object's turn comes from the hand's.
    hand_loss_frames: str = "all"
    # Object pose in metres (models.vq_losses). Off by default: at 10 it cut the held-out
    # object error 155 -> 54 mm but raised the global component's joint error 32 -> 100 mm.
    lambda_obj: float = 0.0
    lambda_vel: float = 0.5
    lambda_cont: float = 0.5


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser and batching (AdamW, batch 64 from the paper; the rest T2M-GPT's)."""

    batch_size: int = 64
    window_frames: int = 128  # training crop length; a multiple of 2**down_t
    lr: float = 2e-4
    weight_decay: float = 0.0
    betas: tuple[float, float] = (0.9, 0.99)
    warmup_iters: int = 1000
    total_iters: int = 200_000
    grad_clip: float = 1.0  # 0 = off
    # Validation on the prepared ``val`` part (when there is one): every val_every steps,
    # the loss over the first val_sequences val sequences whole (as `evaluate` and the engine
    # decode them: a decoder trained on short windows can look fine on windows and not on
    # whole sequences), or, when val_sequences is 0 (configs saved before it), over a fixed
    # draw of val_windows training-length windows; the best weights go to best.pt.
    val_every: int = 250
    val_windows: int = 256
    val_sequences: int = 64


@dataclass(frozen=True)
class VQConfig:
    preset: str
    model: ModelConfig
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> VQConfig:
        m = dict(d["model"])
        m["components"] = tuple(ComponentConfig(**c) for c in m["components"])
        m.setdefault("reset_mode", "absolute")  # configs saved before the mode existed
        m.setdefault("ema_warmup", False)  # ... and before the EMA warm-up
        t = dict(d.get("train", {}))
        t.setdefault("val_sequences", 0)  # configs saved before whole-sequence validation
        if "betas" in t:
            t["betas"] = tuple(t["betas"])
        return VQConfig(
            preset=d["preset"],
            model=ModelConfig(**_known(ModelConfig, m)),
            loss=LossConfig(**_known(LossConfig, d.get("loss", {}))),
            train=TrainConfig(**_known(TrainConfig, t)),
        )

    def save_json(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2))

    @staticmethod
    def load_json(path: str | Path) -> VQConfig:
        return VQConfig.from_dict(json.loads(Path(path).read_text()))


def _known(cls, d: dict) -> dict:
    """Reject unknown keys loudly: a typo in a saved config must not silently fall back."""
    names = {f.name for f in fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return d


# (codebook size, code dim) per component, and the conv width per component.
_CODEBOOKS = {
    "tiny": {"global": (32, 16), "body": (32, 16), "lhand": (32, 16), "rhand": (32, 16)},
    "small": {"global": (256, 64), "body": (512, 128), "lhand": (256, 96), "rhand": (256, 96)},
    "default": {"global": (512, 128), "body": (1024, 256), "lhand": (512, 192), "rhand": (512, 192)},
    "big": {"global": (1024, 256), "body": (2048, 512), "lhand": (1024, 384), "rhand": (1024, 384)},
}
_WIDTHS = {"global": 256, "body": 512, "lhand": 384, "rhand": 384}
# The single-VQ ablation: one codebook the size of the body's, width of the body's.
_SINGLE_FROM = "body"
PRESETS = tuple(_CODEBOOKS)


def make_config(
    preset: str = "default",
    *,
    single: bool = False,
    down_t: int = 4,
    causal_decoder: bool = True,
    width_scale: float = 1.0,
    codebooks: dict[str, int] | None = None,
    **model_overrides,
) -> VQConfig:
    """A preset, optionally as the single-VQ ablation, another ``down_t``, the paper's
    (non-causal) decoder, narrower/wider convs (``width_scale``, e.g. 0.5 for a light
    bundle; widths are rounded to a multiple of 32 so attention heads divide them), or other
    codebook sizes for some components (``codebooks``, e.g. ``{"global": 1024}``)."""
    if preset not in _CODEBOOKS:
        raise ValueError(f"unknown VQ preset {preset!r}; choose one of {PRESETS}")
    books = dict(_CODEBOOKS[preset])
    for name, size in (codebooks or {}).items():
        if name not in books or size < 2:
            raise ValueError(f"codebook override {name}={size}: need a component of {list(books)} and >= 2 codes")
        books[name] = (size, books[name][1])
    tiny = preset == "tiny"

    def width(name: str) -> int:
        base = 32 if tiny else _WIDTHS[name]
        return max(32, int(round(base * width_scale / 32)) * 32)
    if single:
        n, d = books[_SINGLE_FROM]
        comps = (ComponentConfig(SINGLE, n, d, width(_SINGLE_FROM)),)
    else:
        comps = tuple(ComponentConfig(c, *books[c], width(c)) for c in COMPONENTS)
    model = ModelConfig(components=comps, down_t=down_t, causal_decoder=causal_decoder)
    if tiny:
        model = replace(model, res_depth=1, attn_heads=2)
    model = replace(model, **model_overrides)
    fpt = 2**down_t
    if tiny:
        train = TrainConfig(batch_size=4, window_frames=4 * fpt, total_iters=10)
    else:  # about 4 s at 30 fps, at least two tokens
        train = TrainConfig(window_frames=fpt * max(2, 128 // fpt))
    return VQConfig(preset=preset, model=model, train=train)
