"""Physical plausibility of a whole dataset's ground truth, through the metric suite.

Used to check SynthGrasp (and to describe how clean any GRAB-layout data is): per sequence
:func:`metrics.plausibility`, then mean, 95% interval and worst case over sequences.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .body_model import BodyModelConfig, make_body_model
from .grab.reader import load_dataset
from .metrics import MetricConfig, plausibility, sample_from_sequence, summarize
from .representation import resample_sequence


def dataset_plausibility(root: Path, limit: int | None = 100, body: BodyModelConfig | None = None,
                         fps: float = 30.0, cfg: MetricConfig = MetricConfig(), progress: bool = False) -> dict:
    model = make_body_model(body)
    seqs, summary = load_dataset(root, None, "all", limit=limit, progress=progress)
    rows = []
    for seq in seqs:
        s = resample_sequence(seq, fps)
        rows.append(plausibility(sample_from_sequence(s, model), cfg, held_from="labels"))
    stats = summarize(rows)
    return {
        "sequences": summary.loaded, "skipped": summary.skipped, "fps": fps,
        "mean": {k: v.mean for k, v in stats.items()},
        "ci95": {k: v.ci95 for k, v in stats.items()},
        "max": {k: float(np.nanmax([r[k] for r in rows])) for k in stats} if rows else {},
    }
