"""SynthGrasp throughput: sequences generated (plan, synthesis, GRAB file) and read back (the
reader `prepare` uses) per second, in one process.

Imports whichever ``comgrasp_train`` is first on the path, so the same file measures another
checkout; ``scripts/ab_bench.sh`` runs it on this tree and a base commit in interleaved rounds:

    bash scripts/ab_bench.sh scripts/synth_throughput.py sequences_per_s --sequences 12
Prints one JSON line: seconds per sequence to generate and to read, and sequences/s (both).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from comgrasp_train.grab.reader import load_sequence
from comgrasp_train.objects.catalogue import write_object_meshes
from comgrasp_train.synth.generate import generate_sequence, plan_dataset
from comgrasp_train.synth.subjects import write_subject_files


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sequences", type=int, default=12, help="timed sequences (after one untimed)")
    p.add_argument("--first", type=int, default=0, help="index of the first sequence in the seed's plan")
    p.add_argument("--seed", type=int, default=7)
    a = p.parse_args()
    torch.set_num_threads(1)  # as in a `synth --workers N` worker
    specs = plan_dataset(a.first + a.sequences + 1, a.seed)[a.first:]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_object_meshes(root)
        write_subject_files(root)
        generate_sequence(specs[0], root, a.seed)  # caches (meshes, subject models) warm
        t0 = time.perf_counter()
        for spec in specs[1:]:
            generate_sequence(spec, root, a.seed)
        t1 = time.perf_counter()
        for spec in specs[1:]:
            load_sequence(root / spec.file, root)
        t2 = time.perf_counter()
    n = len(specs) - 1
    print(json.dumps({"generate_s_per_seq": round((t1 - t0) / n, 4), "read_s_per_seq": round((t2 - t1) / n, 4),
                      "sequences_per_s": round(n / (t2 - t0), 3)}))


if __name__ == "__main__":
    main()
