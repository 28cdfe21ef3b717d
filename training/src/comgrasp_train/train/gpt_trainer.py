"""Train the four coordinated Transformers on the codes of a trained VQ.

The text encoder runs once over every unique description (they repeat across sequences),
then training samples (text embedding, codes) batches. Codes and embeddings are kept in the
run folder, so a resume does not compute them again (gpt_cache.py). Writes ``<out>/ckpt.pt``
(resumable) + ``config.json`` (transformer, training, VQ run, text encoder) and a log.
When the prepared data has a ``val`` part, its mean NLL per token (every sequence from its
start, first description) is logged as ``val_loss`` beside the training ``loss`` every
``val_every`` steps, and the weights with the lowest one are kept in ``best.pt`` (early
stopping by selection; ``load_gpt`` reads it by default).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import torch

from ..models.gpt_configs import TransformerConfig
from ..models.transformer import ComGraspTransformer, stream_nll
from ..models.vq_losses import make_scheduler
from ..normalization import Normalizer
from ..text_encoder import load_text_encoder
from .gpt_cache import arrays_digest, cached_codes, cached_embeddings, file_stamp, module_digest
from .runtime import TimeLimit, load_checkpoint, load_weights, restore, run_training, seed_everything, setup_runtime
from .tokens import TokenBatcher, encode_feature_set
from .vq_trainer import load_prepared, load_vq


@dataclass(frozen=True)
class GPTTrainConfig:
    batch_size: int = 64
    lr: float = 2e-4
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.99)
    warmup_iters: int = 500
    total_iters: int = 100_000
    grad_clip: float = 1.0
    val_every: int = 250  # validation NLL on the prepared val part, when there is one (0 = off)
    # Share of training sequences whose text embedding is replaced by zeros, the null
    # condition that classifier-free guidance contrasts the text with (sampling.generate).
    text_dropout: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.text_dropout < 1.0:
            raise ValueError(f"text_dropout must be in [0, 1), got {self.text_dropout}")

    @staticmethod
    def from_dict(d: dict) -> GPTTrainConfig:
        known = {f.name for f in fields(GPTTrainConfig)}
        if set(d) - known:
            raise ValueError(f"unknown GPTTrainConfig fields: {sorted(set(d) - known)}")
        d = dict(d)
        if "betas" in d:
            d["betas"] = tuple(d["betas"])
        return GPTTrainConfig(**d)


@dataclass(frozen=True)
class TextConfig:
    backend: str = "minilm"  # "minilm" | "clip" (then checkpoint is required)
    checkpoint: str | None = None
    max_tokens: int | None = None
    weights: str = "fp32"  # "int8" | "int8-tok4": the weights the exported bundle stores (weight_quant.py)


def embed_texts(encoder, texts: list[list[str]], batch: int = 64) -> dict[str, torch.Tensor]:
    unique = sorted({t for variants in texts for t in variants})
    out = {}
    for i in range(0, len(unique), batch):
        chunk = unique[i:i + batch]
        for t, e in zip(chunk, encoder.encode(chunk)):
            out[t] = e.float().cpu()
    return out


def drop_text(emb: torch.Tensor, p: float, gen: torch.Generator) -> torch.Tensor:
    """Each row of (B, d_text) replaced by zeros (the null condition) with probability p.
    Draws from ``gen`` only when p > 0, so runs without it keep their random stream."""
    if p <= 0:
        return emb
    return emb * (torch.rand(len(emb), generator=gen) >= p)[:, None]


def train_gpt(data_dir: Path, vq_dir: Path, out_dir: Path, cfg: TransformerConfig, train: GPTTrainConfig,
              text: TextConfig = TextConfig(), *, seed: int = 0, device: str | None = None, resume: bool = True,
              log_every: int = 50, ckpt_every: int = 1000, progress: bool = True,
              stop_after: int | None = None, time_limit: TimeLimit | None = None) -> dict:
    rt = setup_runtime(device)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seed_everything(seed + rt.rank)
    fs, _ = load_prepared(data_dir, "train")
    # Codes with the normalization the VQ was trained with (its run keeps it), which is not
    # that of ``data_dir`` when the VQ was trained on other or fewer sequences.
    norm = Normalizer.load(Path(vq_dir) / "stats.npz")
    vq, vq_cfg, _ = load_vq(vq_dir, rt.device)
    books = tuple(c.codebook_size for c in vq_cfg.model.components)
    if books != tuple(cfg.codebook_sizes):
        raise ValueError(f"transformer codebook sizes {cfg.codebook_sizes} do not match the VQ's {books}")
    encoder = load_text_encoder(text.backend, checkpoint=text.checkpoint, max_tokens=text.max_tokens,
                                weights=text.weights)
    if encoder.dim != cfg.d_text:
        raise ValueError(f"transformer d_text {cfg.d_text} != text encoder dim {encoder.dim}")
    # Codes and text embeddings are kept in the run folder for resumes (gpt_cache.py).
    vq_key = {"vq": module_digest(vq), "normalization": arrays_digest(norm.mean, norm.std)}

    def codes_of(part: str, part_fs):
        key = {**vq_key, "features": file_stamp(Path(data_dir) / f"features_{part}.npz")}
        return cached_codes(out_dir / f"codes_{part}.npz", key, part_fs,
                            lambda: encode_feature_set(vq, part_fs, norm, rt.device), write=rt.is_main)

    tokens = codes_of("train", fs)
    val_tokens = None
    if (Path(data_dir) / "features_val.npz").is_file() and train.val_every > 0:
        val_tokens = codes_of("val", load_prepared(data_dir, "val")[0])
    vq = None  # not needed past the codes
    val_texts = [t[:1] for t in val_tokens.texts] if val_tokens is not None else []
    embed = cached_embeddings(
        out_dir / "text_emb.npz", {"text": asdict(text), "encoder": module_digest(encoder.network)},
        [t for variants in tokens.texts + val_texts for t in variants],
        lambda missing: embed_texts(encoder, [missing]), write=rt.is_main)
    val_batcher = TokenBatcher(val_tokens, cfg, embed) if val_tokens is not None else None
    batcher = TokenBatcher(tokens, cfg, embed)

    model = ComGraspTransformer(cfg).to(rt.device)
    opt = torch.optim.AdamW(model.parameters(), lr=train.lr, betas=train.betas, weight_decay=train.weight_decay)
    sched = make_scheduler(opt, train)
    gen = torch.Generator().manual_seed(seed + 1000 * rt.rank)
    ckpt_path = out_dir / "ckpt.pt"
    step, best_val = 0, float("inf")
    if resume and ckpt_path.is_file():
        ckpt = load_checkpoint(ckpt_path, rt.device)
        if TransformerConfig.from_dict(ckpt["config"]["transformer"]) != cfg:
            raise ValueError(f"{ckpt_path} was trained with a different transformer config; use a new --out")
        step = restore(ckpt, model=model, optimizer=opt, scheduler=sched)
        if time_limit is None and "time_budget_s" in ckpt["config"]:  # continue the fitted run
            train = replace(train, total_iters=ckpt["config"]["train"]["total_iters"])
        gen.set_state(ckpt["extra"]["sampler_rng"])
        best_val = ckpt["extra"].get("best_val", best_val)
    net = model
    if rt.distributed:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[rt.local_rank] if rt.device.type == "cuda" else None)

    config = {"transformer": cfg.to_dict(), "train": asdict(train), "text": asdict(text), "vq_dir": str(vq_dir),
              "data": str(data_dir), "seed": seed, "fps": fs.fps}

    names = ("global", "body", "lhand", "rhand")

    def one_step():
        emb, codes = batcher.batch(train.batch_size, gen)
        emb = drop_text(emb, train.text_dropout, gen)
        net.train()
        opt.zero_grad(set_to_none=True)
        codes = codes.to(rt.device)
        # Through the (possibly DDP-wrapped) forward so gradients are synchronised.
        loss, per = stream_nll(net(emb.to(rt.device), codes[:, :-1]), codes, cfg.pad_ids)
        loss.backward()
        if train.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(net.parameters(), train.grad_clip)
        opt.step()
        sched.step()
        return {"loss": loss.detach(), **{f"nll/{n}": v.detach() for n, v in zip(names, per)}}

    @torch.no_grad()
    def validate():
        model.eval()
        n = len(val_batcher.ts.codes)
        tot, per_tot, count = 0.0, torch.zeros(4), 0
        for a in range(0, n, train.batch_size):
            idx = list(range(a, min(n, a + train.batch_size)))
            emb, codes = val_batcher.fixed(idx)
            codes = codes.to(rt.device)
            loss, per = stream_nll(model(emb.to(rt.device), codes[:, :-1]), codes, cfg.pad_ids)
            tot += float(loss) * len(idx)
            per_tot += torch.stack(per).float().cpu() * len(idx)
            count += len(idx)
        model.train()
        return {"val_loss": tot / count, **{f"val_nll/{k}": float(v) / count for k, v in zip(names, per_tot)}}

    return run_training(
        rt, step=step, end=min(train.total_iters, stop_after or train.total_iters), total=train.total_iters,
        desc="train-gpt", step_fn=one_step, out_dir=out_dir, model=model, optimizer=opt, scheduler=sched,
        config=config, gen=gen, log_every=log_every, ckpt_every=ckpt_every, progress=progress,
        validate=validate if val_batcher is not None else None, val_every=train.val_every, best_val=best_val,
        time_limit=time_limit)


def load_gpt(run_dir: Path, device="cpu", which: str = "best"):
    """(model in eval mode, TransformerConfig, checkpoint config dict) from a GPT run directory;
    ``which``: ``best`` (``best.pt`` when the run validated, else the last) or ``last``."""
    ckpt = load_weights(Path(run_dir), which, device)
    cfg = TransformerConfig.from_dict(ckpt["config"]["transformer"])
    model = ComGraspTransformer(cfg).to(device)
    model.load_state_dict(ckpt["model"])
    return model.eval(), cfg, {**ckpt["config"], "checkpoint": {"file": ckpt["which"], "step": ckpt["step"]}}
