"""SynthGrasp dataset generation: which sequences, in parallel, written in GRAB's layout.

``generate_dataset`` writes ``<out>/grab/s<k>/<obj>_<intent>_<n>.npz`` (GRAB's exact file
format, read by ``grab.reader`` unchanged), the meshes under ``<out>/tools`` and
``<out>/synthgrasp_index.json`` (one row per file). Sequence i draws from its own random
stream seeded by (seed, i, attempt), so the files do not depend on the number of workers;
the same seed gives byte-identical files.

SynthGrasp specifics a consumer should know: ``contact/body`` indexes the points of the
subject's open surface proxy (``surface.build_proxy`` of ``s<k>_skeleton.npy`` with the
body model's default spacing), not SMPL-X vertices; the MANO PCA ``hand_pose`` entries are
zeros (the hands are in ``fullpose``); ``lhand``/``rhand`` hold the wrist's global rotation
and position and the 15 finger joints' local axis-angles.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from dataclasses import asdict, dataclass
from functools import cache, partial
from pathlib import Path

import numpy as np
import trimesh

from .. import skeleton as sk
from ..grab.format import write_grab_npz
from ..objects.catalogue import CATALOGUE, ObjectSpec, write_object_meshes
from ..parallel import parallel_map
from .ik import matrix_to_rotvec
from .intents import make_plan
from .motion import synthesize
from .plan import FPS, PlanRejected
from .subjects import SUBJECT, SUBJECTS, subject_model, vtemp_path, write_subject_files

INTENTS = ("lift", "pass", "offhand", "inspect", "drink", "pour")
GENERIC_INTENTS = ("lift", "pass", "offhand", "inspect")  # every object; drink/pour per catalogue
MAX_ATTEMPTS = 100  # draws per sequence before giving up (a few are typical)
INDEX_FILE = "synthgrasp_index.json"


def passable(obj: ObjectSpec) -> bool:
    """During a hand-over both hands hold the object and the receiving hand must stay above
    its bottom (it puts it down). Two whole hands (the generator has no fingertip pinch) only
    fit on an object at least ~7 cm tall or ~10 cm wide; GRAB's small cube, sphere and
    pyramids and our medium pyramid are therefore not passed."""
    return obj.half_height >= 0.036 or obj.half_extents[:2].max() >= 0.05


def hand_modes(obj: ObjectSpec, intent: str) -> tuple[str, ...]:
    """Valid hand modes: a pass goes from one hand to the other; two-handed objects are
    otherwise held with both hands, the rest with either hand."""
    if intent == "pass":
        return ("right>left", "left>right") if passable(obj) else ()
    return ("both",) if obj.two_handed else ("left", "right")


def combinations() -> dict[str, list[tuple[str, str]]]:
    """intent -> every valid (object, hand mode)."""
    out: dict[str, list[tuple[str, str]]] = {i: [] for i in INTENTS}
    for name, obj in CATALOGUE.items():
        for intent in GENERIC_INTENTS + obj.uses:
            out[intent] += [(name, mode) for mode in hand_modes(obj, intent)]
    return out


@dataclass(frozen=True)
class SequenceSpec:
    index: int
    sbj_id: str
    gender: str
    obj_name: str
    intent: str
    mode: str
    file: str  # relative to the dataset root

    @property
    def hands(self) -> list[str]:
        """Hands in the order they grasp (both: left and right together)."""
        return self.mode.split(">") if ">" in self.mode else (["left", "right"] if self.mode == "both" else [self.mode])


def plan_dataset(n_sequences: int, seed: int) -> list[SequenceSpec]:
    """Which sequences to make. Intents take turns; within an intent the (object, hand mode)
    combinations cycle with the hand modes interleaved, so any 3 consecutive sequences of an
    intent cover its modes; subjects are dealt evenly at random."""
    rng = np.random.default_rng([seed])
    intents = [INTENTS[i] for i in rng.permutation(len(INTENTS))]
    cycles = {}
    for intent, combos in combinations().items():
        modes = sorted({m for _, m in combos})
        groups = [[c for c in combos if c[1] == m] for m in (modes[i] for i in rng.permutation(len(modes)))]
        groups = [[g[i] for i in rng.permutation(len(g))] for g in groups]
        cycles[intent] = [g[k] for k in range(max(map(len, groups))) for g in groups if k < len(g)]
    subjects = np.tile(np.arange(len(SUBJECTS)), -(-n_sequences // len(SUBJECTS)))[:n_sequences]
    subjects = subjects[rng.permutation(n_sequences)]
    taken: Counter = Counter()
    specs = []
    for i in range(n_sequences):
        intent = intents[i % len(intents)]
        cycle = cycles[intent]
        obj_name, mode = cycle[(i // len(intents)) % len(cycle)]
        sbj = SUBJECTS[subjects[i]]
        taken[(sbj.sbj_id, obj_name, intent)] += 1
        n = taken[(sbj.sbj_id, obj_name, intent)]
        specs.append(SequenceSpec(i, sbj.sbj_id, sbj.gender, obj_name, intent, mode,
                                  f"grab/{sbj.sbj_id}/{obj_name}_{intent}_{n}.npz"))
    return specs


@cache
def _mesh_vertices(path: str) -> np.ndarray:
    return np.asarray(trimesh.load(path, process=False, force="mesh").vertices, dtype=np.float64)


def generate_sequence(spec: SequenceSpec, root: str | Path, seed: int) -> dict:
    """Plan, synthesize and write one sequence (meshes must already be under ``root``);
    returns its index row."""
    root = Path(root)
    obj = CATALOGUE[spec.obj_name]
    mesh = f"tools/object_meshes/contact_meshes/{spec.obj_name}.ply"
    verts = _mesh_vertices(str(root / mesh))
    model = subject_model(spec.sbj_id)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, spec.index, attempt])
        try:
            plan = make_plan(model, obj, verts, spec.intent, spec.mode, rng)
            motion = synthesize(plan)
            break
        except PlanRejected:
            continue
    else:
        raise RuntimeError(f"sequence {spec.index} ({spec.file}): no valid plan in {MAX_ATTEMPTS} attempts")

    T = motion.n_frames
    fullpose = motion.fullpose
    hand = {side: {"global_orient": matrix_to_rotvec(motion.global_rot[:, w]), "transl": motion.joints[:, w],
                   "fullpose": fullpose[:, cols]}
            for side, w, cols in (("lhand", sk.LEFT_WRIST, slice(75, 120)), ("rhand", sk.RIGHT_WRIST, slice(120, 165)))}
    table = np.tile(plan.scene.table_centre, (T, 1))
    write_grab_npz(
        root / spec.file, gender=spec.gender, sbj_id=spec.sbj_id, obj_name=spec.obj_name,
        motion_intent=spec.intent, fullpose=fullpose, transl=motion.transl,
        object_transl=motion.object_pos,
        # GRAB's row-vector convention: global_orient is the axis-angle of R_world^T.
        object_global_orient=matrix_to_rotvec(np.swapaxes(motion.object_rot, -1, -2)),
        table_transl=table, table_global_orient=np.zeros((T, 3)),
        contact_body=motion.contact_body, contact_object=motion.contact_object,
        vtemp=vtemp_path(SUBJECT[spec.sbj_id]), object_mesh=mesh, lhand=hand["lhand"], rhand=hand["rhand"],
    )
    return {**asdict(spec), "hands": spec.hands, "n_frames": T, "seconds": round((T - 1) / FPS, 4),
            "attempts": attempt + 1}


def generate_dataset(out_dir: Path, n_sequences: int, seed: int, workers: int = 2, progress: bool = True) -> dict:
    """Write a SynthGrasp dataset of ``n_sequences`` under ``out_dir`` with ``workers``
    processes (1: in this process). Existing files of the same names are overwritten,
    others are left alone. The index (``synthgrasp_index.json``) has one row per file:
    file, index, sbj_id, gender, obj_name, intent, mode ('left' | 'right' | 'both' |
    'right>left' | 'left>right', a pass being giver>taker), hands (in grasp order),
    n_frames, seconds, attempts (draws it took). Returns the summary: counts per
    intent/object/hands/subject/gender, frames, motion seconds, and the wall-clock
    seconds the generation took."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_object_meshes(out_dir)
    write_subject_files(out_dir)
    specs = plan_dataset(n_sequences, seed)
    job = partial(generate_sequence, root=str(out_dir), seed=seed)
    rows = list(parallel_map(job, specs, workers, progress=progress, desc="SynthGrasp", unit="seq"))
    counts = {key: dict(sorted(Counter(r[field] for r in rows).items()))
              for key, field in (("intent", "intent"), ("object", "obj_name"), ("hands", "mode"),
                                 ("subject", "sbj_id"), ("gender", "gender"))}
    summary = {"sequences": len(rows), "frames": sum(r["n_frames"] for r in rows),
               "motion_seconds": round(sum(r["seconds"] for r in rows), 3), **counts}
    index = {"dataset": "SynthGrasp", "seed": seed, "framerate": FPS, "summary": summary, "files": rows}
    (out_dir / INDEX_FILE).write_text(json.dumps(index, indent=1) + "\n")
    return {**summary, "wall_seconds": round(time.perf_counter() - start, 2)}
