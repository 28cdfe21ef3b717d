"""train-vq throughput: training windows per second of `vq_training_step` on prepared data.

Imports whichever ``comgrasp_train`` is first on the path, so the same file measures another
checkout (``PYTHONPATH=<worktree>/training/src``); ``scripts/vq_throughput.sh`` runs the
current tree and a base commit in interleaved rounds and prints their ratio.

    python scripts/vq_throughput.py --data data/sg3000_prep --preset small --batch 32 --window 64 --steps 8
Prints one JSON line: windows/s, ms per step (median of the timed steps), device.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from comgrasp_train.models.configs import make_config
from comgrasp_train.models.vq_losses import make_optimizer, vq_training_step
from comgrasp_train.models.vqvae import build_vq
from comgrasp_train.representation import features_to_joints
from comgrasp_train.train.vq_trainer import load_prepared
from comgrasp_train.train.windows import WindowSampler


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--preset", default="small")
    p.add_argument("--width-scale", type=float, default=1.0)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--window", type=int, default=64)
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    a = p.parse_args()
    fs, norm = load_prepared(Path(a.data), "train")
    cfg = make_config(a.preset, width_scale=a.width_scale)
    cfg = replace(cfg, train=replace(cfg.train, batch_size=a.batch, window_frames=a.window))
    sampler = WindowSampler(fs, norm, a.window)
    torch.manual_seed(0)
    model = build_vq(cfg.model, a.device)
    opt = make_optimizer(model, cfg)
    mean = torch.as_tensor(norm.mean, device=a.device)
    std = torch.as_tensor(norm.std, device=a.device)
    gen = torch.Generator().manual_seed(0)
    sync = torch.cuda.synchronize if a.device.startswith("cuda") else (lambda: None)
    times = []
    for i in range(a.warmup + a.steps):
        sync()
        t0 = time.perf_counter()
        x, rest = sampler.batch(a.batch, gen)
        x, rb = x.to(a.device), rest.to(a.device)[:, None]
        vq_training_step(model, opt, x, lambda f: features_to_joints(f, rb), cfg, lambda t: t * std + mean)
        sync()
        if i >= a.warmup:
            times.append(time.perf_counter() - t0)
    ms = 1000 * statistics.median(times)
    print(json.dumps({"windows_per_s": round(1000 * a.batch / ms, 2), "ms_per_step": round(ms, 1),
                      "device": a.device, "batch": a.batch, "window": a.window, "preset": a.preset,
                      "width_scale": a.width_scale}))


if __name__ == "__main__":
    main()
