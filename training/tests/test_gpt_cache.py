"""train-gpt's run-folder cache of codes and text embeddings (train/gpt_cache.py): a resume
reuses exactly what a fresh run computed, and a changed VQ, normalisation, features file or
text encoder makes it compute again."""

from __future__ import annotations

import numpy as np
import torch

from comgrasp_train.dataset import FeatureSet
from comgrasp_train.train.gpt_cache import cached_codes, cached_embeddings, file_stamp, module_digest
from comgrasp_train.train.tokens import TokenSet


def _fs(lengths):
    return FeatureSet(fps=30.0, features=[np.zeros((n, 335), np.float32) for n in lengths],
                      texts=[[f"text {i}", f"other {i}"] for i in range(len(lengths))],
                      meta=[{"i": i} for i in range(len(lengths))])


def test_codes_are_reused_under_the_same_key_and_recomputed_under_another(tmp_path):
    fs = _fs([3, 5, 1])
    rng = np.random.default_rng(0)
    made = []

    def encode():
        made.append(1)
        return TokenSet([rng.integers(0, 256, (n, 4)).astype(np.int64) for n in (3, 5, 1)], fs.texts, fs.meta)

    path = tmp_path / "codes_train.npz"
    first = cached_codes(path, {"vq": "a"}, fs, encode)
    again = cached_codes(path, {"vq": "a"}, fs, encode)
    assert len(made) == 1 and path.is_file()
    assert [c.dtype for c in again.codes] == [np.int64] * 3
    assert all(np.array_equal(a, b) for a, b in zip(first.codes, again.codes))
    assert again.texts is fs.texts and again.meta is fs.meta
    other = cached_codes(path, {"vq": "b"}, fs, encode)  # another VQ
    assert len(made) == 2 and not all(np.array_equal(a, b) for a, b in zip(first.codes, other.codes))
    cached_codes(path, {"vq": "b"}, _fs([3, 5]), lambda: made.append(1) or TokenSet([], [], []))  # other sequences
    assert len(made) == 3
    cached_codes(tmp_path / "ro.npz", {"vq": "a"}, fs, encode, write=False)
    assert not (tmp_path / "ro.npz").exists()


def test_embeddings_are_reused_and_only_new_texts_are_embedded(tmp_path):
    asked = []

    def embed(missing):
        asked.append(list(missing))
        return {t: torch.full((4,), float(len(t))) + torch.rand(4) for t in missing}

    path = tmp_path / "text_emb.npz"
    a = cached_embeddings(path, {"enc": 1}, ["b", "a", "b"], embed)
    assert asked == [["a", "b"]] and set(a) == {"a", "b"}
    b = cached_embeddings(path, {"enc": 1}, ["a", "c"], embed)
    assert asked[1:] == [["c"]]
    assert torch.equal(b["a"], a["a"]) and b["a"].dtype == torch.float32  # the same bits
    c = cached_embeddings(path, {"enc": 1}, ["a", "b", "c"], embed)
    assert len(asked) == 2 and torch.equal(c["c"], b["c"]) and torch.equal(c["b"], a["b"])
    cached_embeddings(path, {"enc": 2}, ["a"], embed)  # another encoder: nothing reused
    assert asked[2:] == [["a"]]


def test_module_digest_and_file_stamp_see_changes(tmp_path):
    m = torch.nn.Linear(3, 2)
    m.register_buffer("count", torch.tensor(3))  # 0-d, as the quantizers' counters
    d = module_digest(m)
    assert module_digest(m) == d
    with torch.no_grad():
        m.weight[0, 0] += 1e-6
    assert module_digest(m) != d
    d = module_digest(m)
    m.count += 1
    assert module_digest(m) != d
    f = tmp_path / "features_train.npz"
    f.write_bytes(b"x")
    s = file_stamp(f)
    f.write_bytes(b"xy")
    assert file_stamp(f) != s
