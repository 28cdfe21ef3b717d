"""Train the component VQ-VAEs (or the single-VQ ablation) on a prepared feature set.

Reads ``<data>/features_train.npz`` + ``<data>/stats.npz`` (from ``comgrasp-data prepare``),
writes ``<out>/ckpt.pt`` (resumable, every ``ckpt_every`` steps and at the end) with
``config.json`` beside it, and ``<out>/log.jsonl`` (one line of metrics per log step).
When the prepared data has a ``val`` part, the loss on its first sequences, whole, is logged
(``val_loss``, ``val_joint_mm``, per component ``val_joint_mm/<name>``) and the best weights
are kept in ``<out>/best.pt``, which ``load_vq`` reads by default.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..dataset import FeatureSet
from ..models.configs import VQConfig
from ..models.vq_losses import compute_loss, make_optimizer, make_scheduler, vq_training_step
from ..models.vqvae import build_vq, fit_to_tokens
from ..normalization import Normalizer
from ..representation import features_to_joints
from .runtime import TimeLimit, load_checkpoint, load_weights, restore, run_training, seed_everything, setup_runtime
from .windows import WindowSampler

REST_JOINTS_FILE = "rest_joints.npy"


def load_prepared(data_dir: Path, part: str) -> tuple[FeatureSet, Normalizer]:
    data_dir = Path(data_dir)
    for f in (data_dir / f"features_{part}.npz", data_dir / "stats.npz"):
        if not f.is_file():
            raise FileNotFoundError(f"{f} is missing: run `comgrasp-data prepare ROOT --out {data_dir}` first")
    return FeatureSet.load(data_dir / f"features_{part}.npz"), Normalizer.load(data_dir / "stats.npz")


def _val_batches(fs: FeatureSet, norm: Normalizer, cfg: VQConfig) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The fixed validation inputs: (x, rest joints) batches. Whole sequences (first
    ``val_sequences`` of the subjects in turn, each padded to whole tokens by holding its
    last frame, as ``evaluate`` does), one per batch since their lengths differ; or, with
    ``val_sequences`` 0, one draw (its own generator) of ``val_windows`` training windows."""
    t = cfg.train
    if t.val_sequences > 0:
        fs = fs.spread(t.val_sequences)
        rest = torch.from_numpy(np.stack(fs.rest_joints).astype(np.float32))
        return [(fit_to_tokens(torch.from_numpy(norm.normalize(f.astype(np.float32)))[None],
                               cfg.model.frames_per_token, "pad"), rest[i:i + 1]) for i, f in enumerate(fs.features)]
    x, rest = WindowSampler(fs, norm, t.window_frames).batch(t.val_windows, torch.Generator().manual_seed(12345))
    return [(x[a:a + t.batch_size], rest[a:a + t.batch_size]) for a in range(0, len(x), t.batch_size)]


def train_vq(data_dir: Path, out_dir: Path, cfg: VQConfig, *, seed: int = 0, device: str | None = None,
             resume: bool = True, log_every: int = 50, ckpt_every: int = 1000, progress: bool = True,
             stop_after: int | None = None, time_limit: TimeLimit | None = None) -> dict:
    """Run (or resume) VQ training to ``cfg.train.total_iters`` (or pause at ``stop_after``,
    checkpointed, as an interruption would; or fit the run to ``time_limit``, see
    ``run_training``); returns the last metrics."""
    rt = setup_runtime(device)
    out_dir = Path(out_dir)
    ckpt_path = out_dir / "ckpt.pt"
    fs, norm = load_prepared(data_dir, "train")
    if rt.is_main:
        # The bundle's one skeleton (export): the training subjects' mean rest joints, kept
        # with the run so exporting does not need the data folder.
        out_dir.mkdir(parents=True, exist_ok=True)
        np.save(out_dir / REST_JOINTS_FILE, np.mean(np.stack(fs.rest_joints), axis=0).astype(np.float64))
    seed_everything(seed + rt.rank)
    sampler = WindowSampler(fs, norm, cfg.train.window_frames)
    ckpt = load_checkpoint(ckpt_path, rt.device) if resume and ckpt_path.is_file() else None
    if ckpt is not None:
        saved = VQConfig.from_dict(ckpt["config"]["vq"])
        # A run started before the EMA warm-up existed resumes without it (its saved config).
        if replace(saved.model, ema_warmup=cfg.model.ema_warmup) != cfg.model:
            raise ValueError(f"{ckpt_path} was trained with a different model config; use a new --out")
        # ... and validates as it started (a switch would compare best_val across methods).
        cfg = replace(cfg, model=saved.model, train=replace(cfg.train, val_sequences=saved.train.val_sequences))
        if time_limit is None and "time_budget_s" in ckpt["config"]:  # continue the fitted run
            cfg = replace(cfg, train=replace(cfg.train, total_iters=saved.train.total_iters))
    model = build_vq(cfg.model, rt.device)
    opt = make_optimizer(model, cfg)
    sched = make_scheduler(opt, cfg)
    gen = torch.Generator().manual_seed(seed + 1000 * rt.rank)
    step, best_val = 0, float("inf")
    if ckpt is not None:
        step = restore(ckpt, model=model, optimizer=opt, scheduler=sched)
        gen.set_state(ckpt["extra"]["sampler_rng"])
        best_val = ckpt["extra"].get("best_val", best_val)
    if rt.distributed:
        model = torch.nn.parallel.DistributedDataParallel(model, device_ids=[rt.local_rank] if rt.device.type == "cuda" else None)

    mean = torch.as_tensor(norm.mean, device=rt.device)
    std = torch.as_tensor(norm.std, device=rt.device)

    def denorm(x):
        return x * std + mean

    config = {"vq": cfg.to_dict(), "data": str(data_dir), "seed": seed, "fps": fs.fps}
    out_dir.mkdir(parents=True, exist_ok=True)
    if rt.is_main:  # the run is self-contained: its statistics travel with its checkpoint
        norm.save(out_dir / "stats.npz")

    def one_step():
        x, rest = sampler.batch(cfg.train.batch_size, gen)
        x, rest = x.to(rt.device), rest.to(rt.device)
        rest_b = rest[:, None]  # (B, 1, 55, 3) broadcasts against (B, T, ...) and (P, B, T, ...)
        return vq_training_step(model, opt, x, lambda f: features_to_joints(f, rest_b), cfg, denorm, sched)

    n_comp = len(cfg.model.components)
    validate = None
    if (Path(data_dir) / "features_val.npz").is_file() and cfg.train.val_every > 0:
        val_fs, _ = load_prepared(data_dir, "val")
        batches = _val_batches(val_fs, norm, cfg)
        n_val = sum(len(x) for x, _ in batches)
        core = model.module if rt.distributed else model

        @torch.no_grad()
        def validate():
            core.eval()
            metrics = {}
            for x, rest in batches:
                rb = rest[:, None].to(rt.device)
                _, m = compute_loss(core, x.to(rt.device), lambda f, rb=rb: features_to_joints(f, rb), cfg, denorm)
                for k, v in m.items():
                    metrics[k] = metrics.get(k, 0.0) + float(v) * len(x) / n_val
            core.train()
            out = {"val_loss": metrics["loss"], "val_joint_mm": 1000 * metrics["joint"] / n_comp}
            out.update({f"val_joint_mm/{c.name}": 1000 * metrics[f"joint/{c.name}"] for c in cfg.model.components})
            return out

    return run_training(
        rt, step=step, end=min(cfg.train.total_iters, stop_after or cfg.train.total_iters),
        total=cfg.train.total_iters, desc="train-vq", step_fn=one_step, out_dir=out_dir, model=model,
        optimizer=opt, scheduler=sched, config=config, gen=gen, log_every=log_every, ckpt_every=ckpt_every,
        progress=progress, validate=validate, val_every=cfg.train.val_every, best_val=best_val,
        time_limit=time_limit,
        postfix=lambda m: {"loss": f"{m['loss']:.3f}", "joint_mm": f"{1000 * m['joint'] / n_comp:.1f}"})


def load_vq(run_dir: Path, device: str | torch.device = "cpu", which: str = "best"):
    """(model in eval mode, VQConfig, checkpoint config dict) from a VQ run directory;
    ``which``: ``best`` (``best.pt`` when the run validated, else the last) or ``last``."""
    ckpt = load_weights(Path(run_dir), which, device)
    cfg = VQConfig.from_dict(ckpt["config"]["vq"])
    model = build_vq(cfg.model, device)
    model.load_state_dict(ckpt["model"])
    return model.eval(), cfg, {**ckpt["config"], "checkpoint": {"file": ckpt["which"], "step": ckpt["step"]}}
