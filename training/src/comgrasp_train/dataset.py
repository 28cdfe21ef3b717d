"""Feature sets: a dataset split turned into 335-D sequences + texts, cached on disk.

Reading GRAB is slow (per-vertex contact arrays of ~10^5 values per frame), so training
reads a prepared ``.npz`` made once per split: concatenated features with offsets, each
sequence's rest joints (for the FK joint loss) and its descriptions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .body_model import BodyModelConfig, make_body_model
from .grab.reader import LoadSummary, load_dataset
from .grab.splits import SplitConfig
from .grab.text import describe, hands_from_contact
from .representation import build_features, resample_sequence


@dataclass
class FeatureSet:
    fps: float
    features: list[np.ndarray] = field(default_factory=list)  # (T_i, 335) float32
    rest_joints: list[np.ndarray] = field(default_factory=list)  # (55, 3) per sequence
    texts: list[list[str]] = field(default_factory=list)
    meta: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.features)

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
    def load(path: str | Path) -> "FeatureSet":
        d = np.load(path, allow_pickle=False)
        info = json.loads(str(d["info"]))
        offs = np.concatenate([[0], np.cumsum(d["lengths"])])
        allf = d["features"]  # an NpzFile re-reads the array on every access: read it once
        feats = [allf[a:b] for a, b in zip(offs[:-1], offs[1:])]
        return FeatureSet(float(d["fps"]), feats, list(d["rest_joints"]), info["texts"], info["meta"])


def prepare_features(
    root: str | Path, split: SplitConfig | None, part: str, fps: float = 30.0,
    body: BodyModelConfig | None = None, mention_hands: bool = False, limit: int | None = None,
    progress: bool = False,
) -> tuple[FeatureSet, LoadSummary]:
    """Read a split of a GRAB-layout dataset and build its feature set."""
    model = make_body_model(body)
    seqs, summary = load_dataset(root, split, part, limit=limit, progress=progress)
    out = FeatureSet(fps)
    for seq in seqs:
        subject = model.subject(seq.gender, seq.vtemp)
        s = resample_sequence(seq, fps)
        out.features.append(build_features(s, subject.rest_joints))
        out.rest_joints.append(subject.rest_joints.numpy().astype(np.float32))
        out.texts.append(describe(s.gender, s.intent, s.obj_name, s.contact, mention_hands))
        out.meta.append({
            "name": seq.name, "subject": seq.sbj_id, "gender": seq.gender, "object": seq.obj_name,
            "intent": seq.intent, "object_mesh": seq.object_mesh, "vtemp": seq.vtemp, **hands_from_contact(s.contact),
        })
    return out, summary
