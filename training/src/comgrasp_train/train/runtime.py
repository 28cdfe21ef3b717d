"""Training runtime shared by the VQ and Transformer trainers: device choice, optional DDP
through ``torchrun``, exact checkpoint/resume (model, optimizer, scheduler, every RNG), and
the typed config written beside every checkpoint.

Exact resume means: stopping after step k and resuming gives bit-identical parameters at
step n to an uninterrupted run (same device, deterministic kernels). Quantizer state lives
in registered buffers, so it is part of ``model.state_dict()``.
"""

from __future__ import annotations

import json
import os
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from ..models.vq_losses import capped_warmup


@dataclass
class Runtime:
    device: torch.device
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def setup_runtime(device: str | None = None) -> Runtime:
    """CUDA when available, CPU otherwise; DDP when launched by torchrun (WORLD_SIZE > 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
    rank = dist.get_rank() if world > 1 else 0
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device is None:
        device = f"cuda:{local}" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    return Runtime(dev, rank, world, local)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict:
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, *, model: torch.nn.Module, optimizer, scheduler, step: int,
                    config: dict, extra: dict | None = None) -> None:
    """Atomic write of a resumable checkpoint plus ``config.json`` beside it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    module = model.module if hasattr(model, "module") else model
    payload = {
        "model": module.state_dict(), "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "step": step, "rng": rng_state(), "config": config, "extra": extra or {},
    }
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)
    (path.parent / "config.json").write_text(json.dumps(config, indent=2))


BEST = "best.pt"  # weights of the step with the lowest validation loss (no optimizer state)


def save_weights(path: Path, *, model: torch.nn.Module, step: int, config: dict, metrics: dict) -> None:
    """Atomic write of the model's weights alone (a fraction of a resumable checkpoint)."""
    module = model.module if hasattr(model, "module") else model
    tmp = path.with_suffix(".tmp")
    torch.save({"model": module.state_dict(), "step": step, "config": config, "metrics": metrics}, tmp)
    os.replace(tmp, path)


def load_weights(run_dir: Path, which: str = "best", map_location="cpu") -> dict:
    """The checkpoint to use a trained run with: ``best`` is ``best.pt`` (the lowest
    validation loss) when the run validated, else the last ``ckpt.pt``; ``last`` is ``ckpt.pt``.
    Either way the dict has ``model``, ``config`` and ``step``; ``which`` says what was read."""
    if which not in ("best", "last"):
        raise ValueError(f"which must be 'best' or 'last', got {which!r}")
    run_dir = Path(run_dir)
    path = run_dir / BEST if which == "best" and (run_dir / BEST).is_file() else run_dir / "ckpt.pt"
    ckpt = load_checkpoint(path, map_location)
    ckpt["which"] = path.name
    return ckpt


def load_checkpoint(path: Path, map_location="cpu") -> dict:
    if not Path(path).is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return torch.load(path, map_location=map_location, weights_only=False)


def restore(ckpt: dict, *, model: torch.nn.Module, optimizer=None, scheduler=None) -> int:
    """Load a checkpoint's state into live objects; returns the step to continue from."""
    module = model.module if hasattr(model, "module") else model
    module.load_state_dict(ckpt["model"])
    if optimizer is not None:
        optimizer.load_state_dict(ckpt["optimizer"])
    if scheduler is not None and ckpt.get("scheduler") is not None:
        scheduler.load_state_dict(ckpt["scheduler"])
    set_rng_state(ckpt["rng"])
    return int(ckpt["step"])


@dataclass(frozen=True)
class TimeLimit:
    """How long a run may train: ``seconds`` of its training loop, or until ``deadline`` (Unix
    time), which also counts what the trainer spends loading before its loop (data, codes,
    text embeddings): a script with a fixed allowance then needs no guess of that time."""

    seconds: float | None = None
    deadline: float | None = None

    def __post_init__(self):
        if (self.seconds is None) == (self.deadline is None):
            raise ValueError("a time limit is a number of seconds or a deadline, exactly one of them")

    def budget(self, now: float) -> float:
        """Seconds of training left at ``now``, when the loop starts."""
        if self.seconds is not None:
            return self.seconds
        left = self.deadline - now
        if not left > 0:
            raise ValueError(f"the deadline passed {-left:.0f} s before training started (loading took that long)")
        return left


def run_training(rt: Runtime, *, step: int, end: int, total: int, desc: str, step_fn, out_dir: Path,
                 model, optimizer, scheduler, config: dict, gen: torch.Generator, log_every: int,
                 ckpt_every: int, progress: bool, postfix=None, validate=None, val_every: int = 0,
                 best_val: float = float("inf"), time_limit: TimeLimit | None = None) -> dict:
    """The loop both trainers share: ``step_fn()`` runs one optimisation step and returns its
    metrics (floats or 0-d tensors); every ``log_every`` steps they go to ``log.jsonl`` and the
    progress bar, every ``ckpt_every`` steps and at ``end`` a resumable checkpoint is written
    (with the batch sampler's RNG). With ``validate`` (returns metrics including ``val_loss``;
    must not touch the training RNGs), every ``val_every`` steps and at ``end`` its metrics are
    logged with the step's and the weights go to ``best.pt`` when ``val_loss`` is the lowest
    so far (``best_val``, carried in the checkpoint across resumes).

    With ``time_limit`` (seconds of this loop, or a deadline), the run's length is fitted to it:
    after a few timed steps the remaining steps are set from the measured step time, and
    ``end``, the schedule's ``total`` (its drop lands at two thirds of the fitted run) and the
    saved config's ``total_iters`` change to match (the config also gets ``time_budget_s``,
    the seconds the loop was given); the loop also stops, checkpointed, once the budget is
    spent. For a lent machine with a fixed allowance. Returns the last logged metrics."""
    import time

    # The limit first: a run that cannot start (a passed deadline, torchrun) opens no log.
    fit = None
    if time_limit is not None:
        if rt.distributed:  # each rank would fit its own length, and the collectives would hang
            raise ValueError("a time budget is for single-process training, not torchrun")
        sync = (lambda: torch.cuda.synchronize(rt.device)) if rt.device.type == "cuda" else (lambda: None)
        config["time_budget_s"] = time_limit.budget(time.time())
        fit = BudgetFit(config["time_budget_s"], step, sync)
    log = (out_dir / "log.jsonl").open("a") if rt.is_main else None
    bar = None
    if progress and rt.is_main:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=step, desc=desc, unit="it")
    metrics: dict = {}
    t0 = time.time()
    try:
        while step < end:
            m = step_fn()
            step += 1
            if fit is not None:
                fitted = fit.after_step(step, end)
                if fitted != end:
                    end = total = fitted
                    _set_total(scheduler, config, total)
                    if bar is not None:
                        bar.total = total
                        bar.refresh()
            if bar is not None:
                bar.update(1)
            val = {}
            if validate is not None and rt.is_main and val_every > 0 and (step % val_every == 0 or step == end):
                val = {k: float(v) for k, v in validate().items()}
                if val["val_loss"] < best_val:
                    best_val = val["val_loss"]
                    save_weights(out_dir / BEST, model=model, step=step, config=config, metrics=val)
                val["best_val_loss"] = best_val
            if log is not None and (step % log_every == 0 or step == end or val):
                metrics = {k: float(v) for k, v in m.items()} | val
                metrics.update(step=step, lr=scheduler.get_last_lr()[0], seconds=time.time() - t0)
                log.write(json.dumps(metrics) + "\n")
                log.flush()
                if bar is not None:
                    bar.set_postfix(postfix(metrics) if postfix else {"loss": f"{metrics['loss']:.3f}"})
            if rt.is_main and (step % ckpt_every == 0 or step == end):
                save_checkpoint(out_dir / "ckpt.pt", model=model, optimizer=optimizer, scheduler=scheduler,
                                step=step, config=config, extra={"sampler_rng": gen.get_state(), "best_val": best_val})
    finally:
        if bar is not None:
            bar.close()
        if log is not None:
            log.close()
    return metrics


class BudgetFit:
    """Fits a run to a wall-clock budget: times ``CALIBRATE`` steps after a short warm-up
    (the first steps pay for allocation and kernel selection), sets the end from the
    measured step time with ``MARGIN`` left for validation and checkpoints, and ends the run
    at once when the budget is spent anyway. ``sync`` waits for queued device work (GPU
    steps are asynchronous); ``clock`` is injectable for tests."""

    WARM, CALIBRATE, MARGIN = 5, 20, 0.9

    def __init__(self, budget: float, step0: int, sync=lambda: None, clock=None):
        import time

        if not budget > 0:
            raise ValueError(f"time budget must be positive seconds, got {budget}")
        self.budget, self.step0, self.sync, self.clock = budget, step0, sync, clock or time.monotonic
        self.t_start, self.t_warm, self.fitted = self.clock(), None, False

    def after_step(self, step: int, end: int) -> int:
        """The run's end after ``step`` (``end`` until fitted; then the fitted end, or
        ``step`` once the budget is spent)."""
        done = step - self.step0
        if done == self.WARM:
            self.sync()
            self.t_warm = self.clock()
        elif done == self.WARM + self.CALIBRATE and not self.fitted:
            self.sync()
            now = self.clock()
            per_step = max((now - self.t_warm) / self.CALIBRATE, 1e-9)
            self.fitted = True
            return step + max(1, int(self.MARGIN * (self.budget - (now - self.t_start)) / per_step))
        if self.clock() - self.t_start > self.budget:
            return step
        return end


def _set_total(scheduler, config: dict, total: int) -> None:
    """The fitted run length into the schedule (StepDrop) and the config saved with it."""
    for fn in getattr(scheduler, "lr_lambdas", []):
        if hasattr(fn, "total"):
            fn.total, fn.warmup = total, capped_warmup(fn.warmup, total)
    train = config["vq"]["train"] if "vq" in config else config["train"]
    train["total_iters"], train["warmup_iters"] = total, capped_warmup(train["warmup_iters"], total)
