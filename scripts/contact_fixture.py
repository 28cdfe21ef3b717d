"""Rebuild tests/fixtures/contact_stage: frames that pin the engine's contact stage
(src/contact.rs) and its Python reference (comgrasp_train.contact_stage) to each other.

Each case is a real motion: the release engine's raw output (`comgrasp generate --raw`) for
one prompt and seed on models/default, as de-normalized 335-D features (`input`), the
object's surface samples from the bundle's mesh (`surface`: points and normals, float32),
and what the Python stage makes of it (`output`). training/tests/test_contact_stage.py checks that
the Python stage still gives `output`; tests/contact_stage.rs that the engine's stage gives
it within the manifest's frame tolerance. The motions do not need to come from the current
default model: they only have to exercise the stage's rules, which this script checks
(every rule below must fire in some case).

    cargo build --release && .venv/bin/python scripts/contact_fixture.py

With `--keep-inputs` the motions already stored (`caseK_input.npy`) are kept and only the
stage's outputs are recomputed (after a change to the stage: the same motions, new rules);
cases without a stored input are generated as above.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

from comgrasp_train.contact_stage import ObjectShape, apply_contact_stage, features_from_engine, read_obj, surface_from_mesh

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "fixtures" / "contact_stage"
BUNDLE = ROOT / "models" / "default"
CASES = (  # prompt, seed[, placement from the grasp]: together they make every rule in RULES fire
    ("The woman picks up the banana", 3),
    ("The man is passing the small cylinder from his right hand to his left.", 2),
    ("The man pours from the bowl", 4),
    ("The man is passing the medium sphere from his left hand to his right.", 1),
    ("A woman inspects the small cylinder", 5),
    ("Someone lifts the large sphere with both hands", 6),
    # carried below the table's top until its edge passes under the cube: not set down (thrown up)
    ("Someone grabs the large cube with their left hand and lifts it up", 2),
    # the object where the model put it (the engine's CG_STREAM_NO_GRASP_PLACEMENT): set down tilted
    ("The woman picks up the banana", 3, False),
    # let go just above the table faster than the put-down's budget: the hand holds on for
    # PUT_DOWN_FRAMES more, putting it down, and the rest falls (seed 1 did until the ground
    # drop lowered the floating body that held it)
    ("The woman is lifting the small pyramid with her right hand.", 4),
    # a two-handed set-down that leaves the sphere tilted: it tips
    ("The woman is lifting the large sphere with both hands.", 2),
)
RULES = ("reach", "capture", "release", "recapture", "two_hand_frames", "bow_frames", "press_up", "set_down",
         "fall_frames", "rise_frames", "landed_at_finish", "out_of_reach", "speed_limited", "tip_frames", "level_frames", "reaim", "place_frames",
         "not_set_down_from_below", "press_up_levelling", "not_set_down_tilted", "placed", "kept", "foot_planted",
         "foot_freed", "ground_drop_frames", "put_down_frames")


def main() -> int:
    keep = "--keep-inputs" in sys.argv[1:]
    manifest = json.loads((BUNDLE / "manifest.json").read_text())
    rest = np.asarray(manifest["skeleton"]["rest_joints"], np.float32)
    if keep and (OUT / "rest_joints.npy").is_file():
        # the skeleton the stored motions were made with (the default model may have changed since)
        rest = np.load(OUT / "rest_joints.npy")
    objects = {o["name"]: o for o in manifest["objects"]}
    OUT.mkdir(parents=True, exist_ok=True)
    np.save(OUT / "rest_joints.npy", rest)
    cases, total = [], Counter()
    with tempfile.TemporaryDirectory() as tmp:
        for k, (prompt, seed, *rest_of) in enumerate(CASES):
            place = rest_of[0] if rest_of else True
            stored = OUT / f"case{k}_input.npy"
            old = json.loads((OUT / "index.json").read_text())["cases"] if keep else []
            if keep and stored.is_file() and k < len(old):
                name, x, fps = old[k]["object"], np.load(stored), float(manifest["fps"])
            else:
                npz = Path(tmp) / f"{k}.npz"
                run = subprocess.run([str(ROOT / "target/release/comgrasp"), "generate", "--bundle", str(BUNDLE),
                                      "--text", prompt, "--seed", str(seed), "--raw", "--out", str(npz)],
                                     check=True, capture_output=True, text=True)
                name = re.search(r"; object (\S+) ", run.stdout + run.stderr).group(1)
                frames = dict(np.load(npz))
                x, fps = features_from_engine(frames), float(frames["fps"])
            obj = objects[name]
            # The surface as the engine samples the bundle's mesh, stored (and used) as float32.
            surface = np.concatenate(surface_from_mesh(*read_obj((BUNDLE / obj["mesh"]).read_text())), 1)
            surface = surface.astype(np.float32)
            shape = ObjectShape.of(obj["centre"], obj["half_extents"],
                                   (surface[:, :3].astype(np.float64), surface[:, 3:].astype(np.float64)))
            events = Counter()
            y = apply_contact_stage(x, rest, fps, shape, events, place)
            np.save(OUT / f"case{k}_input.npy", x)
            np.save(OUT / f"case{k}_output.npy", y)
            np.save(OUT / f"case{k}_surface.npy", surface)
            cases.append({"prompt": prompt, "seed": seed, "object": name, "mesh": obj["mesh"], "centre": obj["centre"],
                          "half_extents": obj["half_extents"], "surface": f"case{k}_surface.npy",
                          "input": f"case{k}_input.npy", "output": f"case{k}_output.npy", "frames": len(x),
                          "place": place, "placed": bool(events["placed"]), "events": dict(sorted(events.items()))})
            total += events
            print(f"case{k}: {prompt!r} seed {seed}, {name}, {len(x)} frames: {dict(events)}")
    missing = [r for r in RULES if not total[r]]
    if missing:
        print(f"no case makes these rules fire: {missing}", file=sys.stderr)
        return 1
    index = {"fps": float(manifest["fps"]), "rest_joints": "rest_joints.npy",
             "tolerance": manifest["parity"]["tolerances"]["frames"], "rules": list(RULES), "cases": cases}
    (OUT / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
