"""Reads `comgrasp generate --bvh` output with a BVH parser from PyPI (`bvh`) and checks its
forward kinematics against the engine's own joint positions (`--fk --out F.npz`, glTF
coordinates): every joint of every frame within 1 mm, and the object track against the
frames' object pose. Run by cli/tests/bvh_output.rs; exits non-zero with the worst error.

    python bvh_check.py BODY.bvh OBJECT.bvh FRAMES.npz BUNDLE_DIR

BUNDLE_DIR's manifest names the joints (skeleton.joint_names, in joint order).
"""

import json
import sys
from pathlib import Path

import numpy as np
from bvh import Bvh

AXES = {"X": 0, "Y": 1, "Z": 2}


def rotation(channels, values):
    """The product of the rotation channels in the listed order (column vectors)."""
    r = np.eye(3)
    for name, deg in zip(channels, values):
        if not name.endswith("rotation"):
            continue
        a = np.radians(deg)
        c, s = np.cos(a), np.sin(a)
        i = AXES[name[0]]
        j, k = (i + 1) % 3, (i + 2) % 3
        m = np.eye(3)
        m[j, j], m[j, k], m[k, j], m[k, k] = c, -s, s, c
        r = r @ m
    return r


def fk(mocap):
    """World positions (T, J, 3) and rotations of every joint, cm."""
    names = mocap.get_joints_names()
    t = mocap.nframes
    pos = np.zeros((t, len(names), 3))
    rot = np.zeros((t, len(names), 3, 3))
    for i, name in enumerate(names):
        channels = mocap.joint_channels(name)
        values = np.asarray(mocap.frames_joint_channels(name, channels), float).reshape(t, len(channels))
        offset = np.asarray(mocap.joint_offset(name))
        parent = mocap.joint_parent_index(name)
        for f in range(t):
            local = rotation(channels, values[f])
            if parent < 0:
                p = offset + np.array([values[f][channels.index(f"{a}position")] for a in "XYZ"])
                pos[f, i], rot[f, i] = p, local
            else:
                pos[f, i] = pos[f, parent] + rot[f, parent] @ offset
                rot[f, i] = rot[f, parent] @ local
    return names, pos, rot


def main(body, obj, frames, bundle):
    ref = np.load(frames)
    names, pos, _ = fk(Bvh(open(body).read()))
    want = ref["joint_positions"] * 100.0
    assert pos.shape == want.shape, (pos.shape, want.shape)
    # BVH names are the SMPL-X joint names, depth first: map them to joint order.
    joints = json.loads((Path(bundle) / "manifest.json").read_text())["skeleton"]["joint_names"]
    order = [joints.index(n) for n in names]
    err = np.linalg.norm(pos - want[:, order], axis=-1)
    _, opos, orot = fk(Bvh(open(obj).read()))
    q = ref["object_rotation"].astype(float)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                  2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                  2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
    oerr = np.linalg.norm(opos[:, 0] - ref["object_translation"] * 100.0, axis=-1)
    rerr = np.abs(orot[:, 0] - r).max()
    print(f"{len(names)} joints x {pos.shape[0]} frames: max {err.max():.4f} cm; object {oerr.max():.4f} cm, "
          f"rotation {rerr:.2e}")
    ok = err.max() < 0.1 and oerr.max() < 0.1 and rerr < 1e-4
    return 0 if ok else 1



if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:5]))
