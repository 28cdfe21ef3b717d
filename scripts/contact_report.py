"""Issue 17's contact measurements on the engine's frames, raw against the contact stage.

    python scripts/contact_report.py PROMPTS.tsv DIR > table.md

DIR holds, for the k-th prompt of PROMPTS.tsv (scripts/quality_report.py prompts N) and
seed s, ``p{k}_s{s}_stage.npz`` and ``p{k}_s{s}_raw.npz`` (``comgrasp generate --fk --out``,
the second with ``--raw``). Per stream and mode, over the frames whose contact flag says a
hand holds the object (the stage's decision, or the raw flag):

* hand-object distance: the holding hand's nearest joint (wrist + 15 finger joints) to the
  object's surface (the catalogue SDF), mean and max, mm;
* unheld drift: the largest horizontal object step between two frames no hand holds, mm;
* penetration: the deepest hand joint inside the object over all frames, mm;
* the largest wrist and object speeds, m/s (the object's without the last frame, which
  lands an object still falling at once);
* foot sliding: CHOIS's (``metrics.foot_sliding``: ankles and toes near the floor, their
  horizontal steps weighted by height), mm per frame; the ground truth's is ~0.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from comgrasp_train.grab.text_parse import parse_prompt
from comgrasp_train.intent_check import object_sdf_for, track_from_engine
from comgrasp_train.metrics import foot_sliding

HAND_JOINTS = ((20, *range(25, 40)), (21, *range(40, 55)))


def measure(npz: Path, obj: str) -> dict[str, float]:
    with np.load(npz) as f:
        t = track_from_engine(dict(f), object_sdf_for({"object": obj}))
    # Hand joints in the object's frame, then their surface distance.
    rel = np.einsum("tji,tkj->tki", t.object_rot, t.joints - t.object_transl[:, None])
    d = t.object_sdf(rel.reshape(-1, 3)).reshape(len(rel), -1)
    held = np.asarray(t.contact, bool)
    near = [d[held[:, h]][:, list(HAND_JOINTS[h])].min(axis=1) for h in range(2)]
    near = np.concatenate(near) if any(len(n) for n in near) else np.zeros(0)
    unheld = ~held.any(axis=1)
    steps = np.linalg.norm(np.diff(t.object_transl[:, :2], axis=0), axis=1)
    both = unheld[1:] & unheld[:-1]
    wrist = np.linalg.norm(np.diff(t.joints[:, [20, 21]], axis=0), axis=2) * t.fps
    # Without the last step: the stream's last frame lands an object still falling at once.
    obj_speed = np.linalg.norm(np.diff(t.object_transl[:-1], axis=0), axis=1) * t.fps
    return {
        "held_frames": float(held.any(axis=1).sum()),
        "dist_mean_mm": float(np.clip(near, 0, None).mean() * 1e3) if len(near) else float("nan"),
        "dist_max_mm": float(np.clip(near, 0, None).max() * 1e3) if len(near) else float("nan"),
        "drift_mm": float(steps[both].max() * 1e3) if both.any() else 0.0,
        "penetration_mm": float(max(0.0, -d.min()) * 1e3),
        "wrist_speed": float(wrist.max()),
        "object_speed": float(obj_speed.max()),
        "foot_sliding_mm": foot_sliding(t.joints, t.fps),
    }


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    prompts = [line.split("\t")[0] for line in Path(argv[1]).read_text().splitlines() if line.strip()]
    rows: dict[str, list[dict[str, float]]] = {"raw": [], "stage": []}
    for k, prompt in enumerate(prompts, 1):
        obj = parse_prompt(prompt).object
        for f in sorted(Path(argv[2]).glob(f"p{k}_s*_stage.npz")):
            for mode in ("raw", "stage"):
                rows[mode].append(measure(f.with_name(f.name.replace("_stage", f"_{mode}")), obj))
    keys = ("dist_mean_mm", "dist_max_mm", "drift_mm", "penetration_mm", "wrist_speed", "object_speed",
            "foot_sliding_mm")
    print(f"| mode | streams | held frames | {' | '.join(keys)} |")
    print("|---" * (len(keys) + 3) + "|")
    for mode, r in rows.items():
        held = sum(x["held_frames"] for x in r)
        # Distances: mean over held frames (weighted), max over streams; the rest: max (mean).
        w = np.array([x["held_frames"] for x in r])
        mean = np.nansum([x["dist_mean_mm"] * x["held_frames"] for x in r]) / max(w.sum(), 1)
        cells = [f"{mean:.1f}", f"{np.nanmax([x['dist_max_mm'] for x in r]):.1f}"]
        for key in keys[2:]:
            v = np.array([x[key] for x in r])
            cells.append(f"{v.max():.2f} ({v.mean():.2f})")
        print(f"| {mode} | {len(r)} | {held:.0f} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
