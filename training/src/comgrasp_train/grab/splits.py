"""Named subject splits of GRAB (reference §3), usable on SynthGrasp too.

``diffgrasp``/``imos``: test s10 (DiffGrasp validates on s9, IMoS on s1); ``saga``: test s9,
s10; ``paper``: the ComGrasp paper's "8 train / 2 test" subjects (which two is not stated;
we take s9 and s10, SAGA's choice). DiffGrasp's exclusion of five objects is available as
``diffgrasp_unseen`` (those objects are dropped from every part). ``synthgrasp`` (ours, the
default model's): the paper's test subjects plus s8 as the validation subject, so training
can select checkpoints and stop early without looking at the test subjects.
"""

from __future__ import annotations

from dataclasses import dataclass

ALL_SUBJECTS = tuple(f"s{i}" for i in range(1, 11))


@dataclass(frozen=True)
class SplitConfig:
    name: str
    test: tuple[str, ...]
    val: tuple[str, ...] = ()
    exclude_objects: tuple[str, ...] = ()
    all_subjects: tuple[str, ...] = ALL_SUBJECTS

    def subjects(self, part: str) -> list[str]:
        if part == "test":
            return list(self.test)
        if part == "val":
            return list(self.val)
        if part == "train":
            return [s for s in self.all_subjects if s not in self.test and s not in self.val]
        if part == "all":
            return list(self.all_subjects)
        raise ValueError(f"unknown split part {part!r} (train|val|test|all)")

    def keeps(self, subject: str, file_stem: str) -> bool:
        obj = file_stem.split("_")[0]
        return obj not in self.exclude_objects


SPLITS: dict[str, SplitConfig] = {
    "diffgrasp": SplitConfig("diffgrasp", test=("s10",), val=("s9",)),
    "imos": SplitConfig("imos", test=("s10",), val=("s1",)),
    "saga": SplitConfig("saga", test=("s9", "s10")),
    "paper": SplitConfig("paper", test=("s9", "s10")),
    "synthgrasp": SplitConfig("synthgrasp", test=("s9", "s10"), val=("s8",)),
    "diffgrasp_unseen": SplitConfig(
        "diffgrasp_unseen", test=("s10",), val=("s9",),
        exclude_objects=("apple", "toothbrush", "train", "cubelarge", "phone"),
    ),
}


def get_split(name: str) -> SplitConfig:
    try:
        return SPLITS[name]
    except KeyError:
        raise ValueError(f"unknown split {name!r}; choose one of {sorted(SPLITS)}") from None
