"""The collars' neutral in retargeting: where each source's collar bone points on average, measured once.

Retargeting gives each canonical bone its source bone's world direction. For the limbs that is the
person's own motion; for the collar bone it is mostly a convention, because each skeleton's author put
the collar joint somewhere else (CMU's ASF clavicles start at the neck's base and rise 22 deg to the
shoulder; Daz's start at the sternum and fall 13 deg, and in data v4's Daz clips they never move;
Bandai's run level and 15 deg back). Copied as they are, the canonical shoulders of one source sat
8.5 cm higher against the chest than another's, and the model, which cannot tell the sources apart,
learnt their average: on val's unseen people (86 % Daz) its shoulders were 1.9 cm too high and 2.1 cm
behind.

So each folder's mean collar direction in the chest frame is the canonical rest direction (level,
straight out): retargeting turns the source collar by the rotation that takes that mean to the rest
(a swing, in the chest frame), and keeps the collar's motion about it (a shrug is still a shrug).

    python -m motion.collars [--data ../shared/mocap] [--clips 80]

prints the table below, measured on the train clips of each folder, and the shoulders' shift it makes.
"""
from pathlib import Path

import numpy as np

from motion.hands import measured_from_command_line, train_clips_by_folder
from motion.neutrals import COLLAR_NEUTRAL  # noqa: F401  (the table this module measures)

def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def measure(root, clips=80, seed=0, step=4):
    """{folder: {"skeleton": name, "l": [3], "r": [3]}}: the collar bone's mean unit direction in the chest
    frame over up to `clips` train clips a folder, retargeted without the neutral."""
    from edge import quat
    from edge.skeleton import JOINT, OFFSETS
    from motion import bvh
    from motion.retarget import detect_source, retarget
    out = {}
    for folder, files in train_clips_by_folder(root, clips, seed).items():
        dirs = {"l": [], "r": []}
        skeleton = None
        for f in files:
            clip = bvh.load(Path(root) / f)
            skeleton = detect_source(clip)
            motion, _ = retarget(clip, skeleton, hands=False, collars=False)
            for side in "lr":
                rest = _unit(OFFSETS[JOINT[f"{side}_shoulder"]])
                local = motion.rotations[::step, JOINT[f"{side}_collar"]]
                dirs[side].append(quat.rotate(local, np.broadcast_to(rest, local.shape[:-1] + (3,))))
        out[folder] = {"skeleton": skeleton, **{s: _unit(np.concatenate(dirs[s]).mean(0)) for s in "lr"}}
    return out


def main():
    from edge.skeleton import JOINT, OFFSETS
    m = measured_from_command_line(__doc__, measure)
    length = np.linalg.norm(OFFSETS[JOINT["l_shoulder"]])
    print(f"the collar bone's mean direction in the chest frame, per folder, and how far the neutral moves the "
          f"shoulder ({length * 100:.0f} cm collars; x out, y up, z forward, cm)")
    for folder, d in m.items():
        for side in "lr":
            rest = _unit(OFFSETS[JOINT[f"{side}_shoulder"]])
            shift = (rest - d[side]) * length * 100
            print(f"  {folder:24s} {side}  mean {np.round(d[side], 3)}   shoulder moves {np.round(shift, 1)}")
    print("\nCOLLAR_NEUTRAL = {")
    for folder, d in m.items():
        q = {s: ", ".join(f"{v:.4f}" for v in d[s]) for s in "lr"}
        print(f'    "{folder}": {{"l": ({q["l"]}), "r": ({q["r"]})}},  # {d["skeleton"]}')
    print("}")


if __name__ == "__main__":
    main()
