"""Feature sets: a dataset split turned into 335-D sequences + texts, cached on disk.

Reading GRAB is slow (per-vertex contact arrays of ~10^5 values per frame), so training
reads a prepared ``.npz`` made once per split: concatenated features with offsets, each
sequence's rest joints (for the FK joint loss) and its descriptions.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from .body_model import BodyModelConfig, make_body_model
from .grab.paraphrase import Meaning
from .grab.paraphrase import paraphrases as paraphrase
from .grab.reader import GrabFormatError, LoadSummary, load_sequence, split_files
from .grab.splits import SplitConfig
from .grab.text import describe, hands_from_contact
from .parallel import parallel_map
from .representation import build_features, resample_sequence

log = logging.getLogger(__name__)


@dataclass
class FeatureSet:
    fps: float
    features: list[np.ndarray] = field(default_factory=list)  # (T_i, 335) float32
    rest_joints: list[np.ndarray] = field(default_factory=list)  # (55, 3) per sequence
    texts: list[list[str]] = field(default_factory=list)
    meta: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.features)

    def spread(self, n: int | None) -> FeatureSet:
        """At most ``n`` sequences, taken from each subject in turn (each subject's in order;
        the set's order kept): a limit that covers every subject. A prepared split lists its
        sequences subject by subject, so its first 100 were all one test subject's. The
        whole set when ``n`` is None or not smaller."""
        if n is None or n >= len(self):
            return self
        by_subject: dict[str, list[int]] = {}
        for i, m in enumerate(self.meta):
            by_subject.setdefault(str(m.get("subject")), []).append(i)
        picked, turn = [], 0
        while len(picked) < n:
            picked += [ids[turn] for ids in by_subject.values() if turn < len(ids)][: n - len(picked)]
            turn += 1
        keep = sorted(picked)
        return FeatureSet(self.fps, [self.features[i] for i in keep], [self.rest_joints[i] for i in keep],
                          [self.texts[i] for i in keep], [self.meta[i] for i in keep])

    def save(self, path: str | Path) -> None:
        lengths = np.array([len(f) for f in self.features], dtype=np.int64)
        np.savez(
            path, fps=np.array(self.fps),
            features=np.concatenate(self.features) if self.features else np.zeros((0, 335), np.float32),
            lengths=lengths,
            rest_joints=np.stack(self.rest_joints) if self.rest_joints else np.zeros((0, 55, 3)),
            info=np.array(json.dumps({"texts": self.texts, "meta": self.meta})),
        )

    @staticmethod
    def load(path: str | Path) -> FeatureSet:
        d = np.load(path, allow_pickle=False)
        info = json.loads(str(d["info"]))
        offs = np.concatenate([[0], np.cumsum(d["lengths"])])
        allf = d["features"]  # an NpzFile re-reads the array on every access: read it once
        feats = [allf[a:b] for a, b in zip(offs[:-1], offs[1:])]
        return FeatureSet(float(d["fps"]), feats, list(d["rest_joints"]), info["texts"], info["meta"])


def prepare_features(
    root: str | Path, split: SplitConfig | None, part: str, fps: float = 30.0,
    body: BodyModelConfig | None = None, mention_hands: bool = False, limit: int | None = None,
    progress: bool = False, workers: int = 1, paraphrases: int = 0,
) -> tuple[FeatureSet, LoadSummary]:
    """Read a split of a GRAB-layout dataset and build its feature set, one file per job in
    ``workers`` processes (the result does not depend on their number). Bad files are
    skipped with a logged message and counted, as ``load_dataset`` does.

    Each sequence's texts are the paper's template variants (the first is the canonical
    one, which ``grab.text_parse`` reads back), then ``paraphrases`` training wordings of
    ``grab.paraphrase`` (seeded by the sequence name)."""
    files = split_files(root, split, part, limit)
    job = partial(_prepare_one, root=str(root), fps=fps, body=body, mention_hands=mention_hands,
                  paraphrases=paraphrases)
    out, summary = FeatureSet(fps), LoadSummary()
    for r in parallel_map(job, files, workers, progress=progress, desc=f"preparing {part}", unit="seq"):
        if isinstance(r, str):
            summary.skipped += 1
            summary.problems.append(r)
            log.warning("skipping %s", r)
            continue
        summary.loaded += 1
        for key, value in zip(("features", "rest_joints", "texts", "meta"), r):
            getattr(out, key).append(value)
    return out, summary


_BODY_MODELS: dict[str, object] = {}  # per process: a worker builds its body model once


def _body_model(body: BodyModelConfig | None):
    key = repr(body)
    if key not in _BODY_MODELS:
        _BODY_MODELS[key] = make_body_model(body)
    return _BODY_MODELS[key]


def _prepare_one(file: Path, root: str, fps: float, body: BodyModelConfig | None, mention_hands: bool,
                 paraphrases: int):
    """(features, rest joints, texts, meta) of one file, or the problem as a string."""
    try:
        seq = load_sequence(file, root)
    except GrabFormatError as e:
        return str(e)
    subject = _body_model(body).subject(seq.gender, seq.vtemp)
    s = resample_sequence(seq, fps)
    meta = {
        "name": seq.name, "subject": seq.sbj_id, "gender": seq.gender, "object": seq.obj_name,
        "intent": seq.intent, "object_mesh": seq.object_mesh, "vtemp": seq.vtemp, **hands_from_contact(s.contact),
    }
    texts = describe(s.gender, s.intent, s.obj_name, s.contact, mention_hands)
    if paraphrases:
        meaning = Meaning.of(meta if mention_hands else {**meta, "hands": None, "first": None, "last": None})
        texts += [t for t in paraphrase(meaning, paraphrases, seq.name) if t not in texts]
    return (build_features(s, subject.rest_joints), subject.rest_joints.numpy().astype(np.float32), texts, meta)
