"""The 335-D per-frame layout (DESIGN §2): slices, components, channel groups.

This is a contract with the engine (the bundle manifest carries the same table).
"""

from __future__ import annotations

from dataclasses import dataclass

FRAME_DIM = 335


@dataclass(frozen=True)
class Field:
    name: str
    start: int
    stop: int
    component: str

    @property
    def size(self) -> int:
        return self.stop - self.start

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


FIELDS: tuple[Field, ...] = (
    Field("root_rot6d", 0, 6, "global"),
    Field("root_transl", 6, 9, "global"),  # world pelvis position (J_0 + transl), metres
    Field("object_rot6d", 9, 15, "global"),  # column-vector world rotation of the object
    Field("object_transl", 15, 18, "global"),
    Field("object_centre", 18, 21, "global"),  # object bbox centre in world coordinates
    Field("body_rot6d", 21, 147, "body"),  # joints 1..21
    Field("lhand_rot6d", 147, 237, "lhand"),  # joints 25..39
    Field("lwrist_to_object", 237, 240, "lhand"),  # left wrist position minus object centre
    Field("lcontact", 240, 241, "lhand"),
    Field("rhand_rot6d", 241, 331, "rhand"),  # joints 40..54
    Field("rwrist_to_object", 331, 334, "rhand"),
    Field("rcontact", 334, 335, "rhand"),
)
FIELD = {f.name: f for f in FIELDS}

COMPONENTS: tuple[str, ...] = ("global", "body", "lhand", "rhand")
COMPONENT_SLICES: dict[str, slice] = {
    "global": slice(0, 21),
    "body": slice(21, 147),
    "lhand": slice(147, 241),
    "rhand": slice(241, 335),
}
COMPONENT_DIMS: dict[str, int] = {k: s.stop - s.start for k, s in COMPONENT_SLICES.items()}

# Binary channels (BCE in the VQ loss, not normalized by std).
CONTACT_CHANNELS: tuple[int, ...] = (240, 334)

# Which joints' 6D sits in which slice (joint index -> start column).
ROT6D_JOINT_COLUMNS: dict[int, int] = {0: 0}
ROT6D_JOINT_COLUMNS.update({j: 21 + 6 * (j - 1) for j in range(1, 22)})
ROT6D_JOINT_COLUMNS.update({j: 147 + 6 * (j - 25) for j in range(25, 40)})
ROT6D_JOINT_COLUMNS.update({j: 241 + 6 * (j - 40) for j in range(40, 55)})

assert sum(f.size for f in FIELDS) == FRAME_DIM
assert all(a.stop == b.start for a, b in zip(FIELDS, FIELDS[1:]))
