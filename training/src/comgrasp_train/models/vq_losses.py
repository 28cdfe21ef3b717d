"""VQ-VAE objective and one optimisation step (paper Sec. IV-A).

Per component c (losses are summed over components, so training the container equals
training the four tokenizers independently, each with its own loss scale):

    L_c = L1_param,c + lambda_joint * L1_joint,c + lambda_hand * L1_hand,c + lambda_obj * L1_obj,c
          + lambda_vel * L1_vel,c + lambda_cont * BCE_c (hand components only) + beta * commit_c

* L1_param: mean |x_hat - x| over the component's non-contact channels (normalized space).
* L1_vel:   the same on first differences in time.
* BCE:      on the component's contact channels; the decoder emits logits there.
* L1_obj:   mean |P(h_c) - P(x)| (metres) over four points of the object (its origin and a
  point 10 cm along each of its axes): the object's pose has no joints, and with the joint
  loss alone the global component left the object ~15 cm from where it was (docs/training.md).
* L1_hand:  mean |A(h_c) - A(x)| (metres) over the points ``HAND_LEVER`` along each axis of
  each hand's frame (``hand_axes``, built from the FK wrist and knuckles). A grasped object
  turns with the hand's frame, but a turn about the forearm (a pour) moves the knuckles only
  ~3 cm, so the joint loss, averaged over 55 joints, let the body VQ reconstruct a 54-86 deg
  pour as a 5-29 deg one (docs/training.md). With ``hand_loss_frames = "held"``, the mean
  over the frames where that hand holds the object only.
* L1_joint: mean |FK(h_c) - FK(x)| over all 55 joints (metres), where h_c is the ground
  truth frame with only component c's slice replaced by its reconstruction, so each
  component is charged for its own joint error and no gradient crosses components. FK
  is the caller's ``joints_fn`` on de-normalized features (``denormalize`` maps normalized
  to de-normalized, identity when None), e.g.
  ``lambda x: representation.features_to_joints(x, rest_joints)``. ``joints_fn`` must
  accept extra leading dims: it gets (P, B, T, 335) and returns (P, B, T, J, 3).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from .. import skeleton as sk
from ..layout import CONTACT_CHANNELS, FIELD
from ..rotations import rotation_6d_to_matrix
from .configs import LossConfig, TrainConfig, VQConfig
from .vqvae import ComponentVQ

Fn = Callable[[torch.Tensor], torch.Tensor]


def _core(model: nn.Module) -> ComponentVQ:
    return getattr(model, "module", model)  # unwrap DistributedDataParallel


def _per_component(per_channel: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(335,) per-channel means -> (P,) means over each component's masked channels (0 if none)."""
    m = mask.to(per_channel.dtype)
    return (m @ per_channel) / m.sum(-1).clamp_min(1.0)


def compute_loss(
    model: nn.Module, x: torch.Tensor, joints_fn: Fn, cfg: LossConfig | VQConfig, denormalize: Fn | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """x: (B, T, 335) normalized features (contact 0/1). Returns the loss and detached metrics
    (per component ``<metric>/<name>`` and totals; call ``.item()`` when logging)."""
    cfg = cfg.loss if isinstance(cfg, VQConfig) else cfg
    vq = _core(model)
    out = model(x)
    feat = vq.to_features(out.raw)
    comp = vq.component_mask  # (P, 335)
    cont = list(CONTACT_CHANNELS)
    param_mask = comp.clone()
    param_mask[:, cont] = False

    l_param = _per_component((feat - x).abs().mean((0, 1)), param_mask)
    l_vel = _per_component((feat.diff(dim=1) - x.diff(dim=1)).abs().mean((0, 1)), param_mask)
    bce = F.binary_cross_entropy_with_logits(out.raw[..., cont], x[..., cont], reduction="none").mean((0, 1))
    l_cont = _per_component(bce, comp[:, cont])

    dn = denormalize or (lambda t: t)
    hybrid = dn(torch.where(comp[:, None, None, :], feat[None], x[None]))  # (P, B, T, 335)
    x_dn = dn(x)
    with torch.no_grad():
        j_true = joints_fn(x_dn)
    j_hybrid = joints_fn(hybrid)
    l_joint = (j_hybrid - j_true[None]).abs().flatten(1).mean(1)
    if cfg.lambda_hand:  # from the joints already computed: no second FK
        d = HAND_LEVER * (hand_axes(j_hybrid) - hand_axes(j_true)[None]).abs().mean((-2, -1))  # (P, B, T, 2)
        if cfg.hand_loss_frames == "held":  # contact labels [left, right], the order of hand_axes
            w = (x[..., cont] > 0.5).to(d.dtype)
            l_hand = (d * w).flatten(1).sum(1) / w.sum().clamp(min=1.0)
        elif cfg.hand_loss_frames == "all":
            l_hand = d.flatten(1).mean(1)
        else:
            raise ValueError(f"hand_loss_frames must be 'all' or 'held', got {cfg.hand_loss_frames!r}")
    else:
        l_hand = torch.zeros_like(l_joint)
    if cfg.lambda_obj:
        l_obj = (object_points(hybrid) - object_points(x_dn)[None]).abs().flatten(1).mean(1)
    else:  # off (the default): not even computed
        l_obj = torch.zeros_like(l_joint)

    per = (l_param + cfg.lambda_joint * l_joint + cfg.lambda_hand * l_hand + cfg.lambda_obj * l_obj + cfg.lambda_vel * l_vel
           + cfg.lambda_cont * l_cont + cfg.beta * out.commit)
    loss = per.sum()
    metrics = {"loss": loss.detach()}
    for key, v in (("param", l_param), ("joint", l_joint), ("hand", l_hand), ("obj", l_obj), ("vel", l_vel), ("cont", l_cont),
                   ("commit", out.commit), ("perplexity", out.perplexity), ("resets", out.resets),
                   ("used", out.used), ("loss", per)):
        v = v.detach()
        if key != "loss":
            metrics[key] = v.mean() if key in ("perplexity", "used") else v.sum()
        for name, val in zip(vq.names, v):
            metrics[f"{key}/{name}"] = val
    return loss, metrics


HAND_LEVER = 0.2  # metres: about where a held object's far side is from the wrist
# Per side (wrist, middle1, index1, pinky1): the hand's long axis runs wrist -> middle
# knuckle, its width index -> pinky knuckle. All are FK children of the wrist, so the
# frame turns exactly as the wrist's global rotation does.
_HAND_FRAME_JOINTS = tuple(
    (wrist, *(sk.JOINT_NAMES.index(f"{side}_{n}1") for n in ("middle", "index", "pinky")))
    for side, wrist in (("left", sk.LEFT_WRIST), ("right", sk.RIGHT_WRIST)))


def hand_axes(j: torch.Tensor) -> torch.Tensor:
    """FK joints (..., 55, 3) -> (..., 2, 3, 3): the unit axes (long, across, palm normal) of
    the left and right hand's frame, in world coordinates."""
    idx = torch.tensor(_HAND_FRAME_JOINTS, device=j.device)
    p = j[..., idx.flatten(), :].unflatten(-2, idx.shape)  # (..., 2, 4, 3)
    long = F.normalize(p[..., 1, :] - p[..., 0, :], dim=-1)
    width = p[..., 2, :] - p[..., 3, :]
    normal = F.normalize(torch.linalg.cross(long, width, dim=-1), dim=-1)
    across = torch.linalg.cross(normal, long, dim=-1)
    return torch.stack([long, across, normal], -2)


OBJECT_POINT_OFFSET = 0.1  # metres along each object axis: rotation errors weigh like translation


def object_points(f: torch.Tensor) -> torch.Tensor:
    """De-normalized (..., 335) features -> (..., 4, 3): the object's origin and the points
    ``OBJECT_POINT_OFFSET`` along each of its axes, in world coordinates."""
    t = f[..., FIELD["object_transl"].slice]
    axes = rotation_6d_to_matrix(f[..., FIELD["object_rot6d"].slice]).transpose(-1, -2)  # rows: R's columns
    return torch.cat([t[..., None, :], t[..., None, :] + OBJECT_POINT_OFFSET * axes], -2)


def make_optimizer(model: nn.Module, cfg: TrainConfig | VQConfig) -> torch.optim.Optimizer:
    cfg = cfg.train if isinstance(cfg, VQConfig) else cfg
    return torch.optim.AdamW(model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay)


def capped_warmup(warmup: int, total: int) -> int:
    """The warm-up a run of ``total`` steps gets: at most a tenth of it (and at least 1)."""
    return min(warmup, max(1, total // 10))


class StepDrop:
    """Linear warm-up, then T2M-GPT's single x0.05 drop at two thirds of ``total``. A callable
    object rather than a closure so LambdaLR saves ``total`` with the checkpoint: a run whose
    length was fitted to a time budget (``run_training``) resumes with the same schedule."""

    def __init__(self, warmup: int, total: int):
        self.warmup, self.total = max(warmup, 1), total

    def __call__(self, it: int) -> float:
        return min(1.0, (it + 1) / self.warmup) * (0.05 if it >= (2 * self.total) // 3 else 1.0)


def make_scheduler(optimizer: torch.optim.Optimizer, cfg: TrainConfig | VQConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up, then T2M-GPT's single x0.05 drop at two thirds of the run (StepDrop)."""
    cfg = cfg.train if isinstance(cfg, VQConfig) else cfg
    return torch.optim.lr_scheduler.LambdaLR(optimizer, StepDrop(cfg.warmup_iters, cfg.total_iters))


def vq_training_step(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    x: torch.Tensor,
    joints_fn: Fn,
    cfg: VQConfig,
    denormalize: Fn | None = None,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
) -> dict[str, torch.Tensor]:
    """One AdamW step on a (B, T, 335) normalized batch; returns the detached metrics."""
    model.train()
    optimizer.zero_grad(set_to_none=True)
    loss, metrics = compute_loss(model, x, joints_fn, cfg, denormalize)
    loss.backward()
    if cfg.train.grad_clip > 0:
        metrics["grad_norm"] = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.train.grad_clip).detach()
    optimizer.step()
    if scheduler is not None:
        scheduler.step()
    return metrics
