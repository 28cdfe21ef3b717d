"""What train-gpt computes before its first step, kept in the run folder for its resumes.

Encoding every training sequence with the VQ and every description with the text encoder
is a fixed cost paid again by every resume: on the 2-core CPU machine, 10,000 SynthGrasp
sequences (112,000 descriptions) took longer than half an hour before the first step. A CPU
run is resumed session after session, so both are kept in the run folder:

* ``codes_<part>.npz``: the codes of each sequence, valid while the VQ's weights, its
  normalisation and the prepared features file (path, size, modification time) are those it
  was made with;
* ``text_emb.npz``: an embedding per description, valid while the text encoder's settings
  and weights are those it was made with; descriptions it lacks are embedded and added.

The key of each file is a digest of what it depends on, so a stale file is recomputed, never
reused. Values are stored exactly (int64 codes, float32 embeddings): a resumed run trains on
the same bits as a fresh one.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..dataset import FeatureSet
from .tokens import TokenSet


def module_digest(module: torch.nn.Module) -> str:
    """sha256 over a module's state (names, dtypes, shapes, bytes)."""
    h = hashlib.sha256()
    for name, t in module.state_dict().items():
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        t = t.detach().cpu().contiguous().reshape(-1)  # (a 0-d tensor cannot be viewed as bytes)
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def arrays_digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def file_stamp(path: Path) -> dict:
    """Which file, as of when: prepare rewrites its outputs, so size and mtime change."""
    st = Path(path).stat()
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _key_text(key: dict) -> str:
    return json.dumps(key, sort_keys=True)


def _stored_key(z) -> str | None:
    return str(z["key"]) if "key" in z.files else None


def _save(path: Path, **arrays) -> None:
    """Written beside and renamed, so a run stopped mid-write leaves no torn file."""
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def cached_codes(path: Path, key: dict, fs: FeatureSet, encode: Callable[[], TokenSet], write: bool = True) -> TokenSet:
    """The token set of ``fs`` from ``path`` when its key is ``key``, else ``encode()`` (saved
    to ``path`` when ``write``)."""
    path, k = Path(path), _key_text(key)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if _stored_key(z) == k and len(z["lengths"]) == len(fs.features):
                lengths, flat = z["lengths"], z["codes"]
                codes = list(np.split(flat, np.cumsum(lengths)[:-1])) if len(lengths) else []
                return TokenSet([c.copy() for c in codes], fs.texts, fs.meta)
    ts = encode()
    if write:
        lengths = np.array([len(c) for c in ts.codes], dtype=np.int64)
        flat = np.concatenate(ts.codes) if ts.codes else np.zeros((0, 4), np.int64)
        _save(path, key=np.array(k), lengths=lengths, codes=flat)
    return ts


def cached_embeddings(path: Path, key: dict, texts: list[str], embed: Callable[[list[str]], dict[str, torch.Tensor]],
                      write: bool = True) -> dict[str, torch.Tensor]:
    """{text: embedding} for every text: those ``path`` holds under ``key``, the rest from
    ``embed(missing)`` (and ``path`` rewritten with all of them when ``write``)."""
    path, k = Path(path), _key_text(key)
    have: dict[str, torch.Tensor] = {}
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if _stored_key(z) == k:
                have = {str(t): torch.from_numpy(e.copy()) for t, e in zip(z["texts"], z["emb"])}
    wanted = sorted(set(texts))
    missing = [t for t in wanted if t not in have]
    if missing:
        have.update(embed(missing))
        if write:
            keep = sorted(have)
            _save(path, key=np.array(k), texts=np.array(keep),
                  emb=torch.stack([have[t] for t in keep]).numpy().astype(np.float32))
    return {t: have[t] for t in wanted}
