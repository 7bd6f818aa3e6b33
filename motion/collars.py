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

from motion.hands import measured_from_command_line, neutral_in, skeleton_means, train_clips_by_folder

# Folder -> side -> the collar bone's mean unit direction in the canonical chest frame (x left, y up,
# z forward), as retargeting without the neutral gives it. Measured by `python -m motion.collars` on
# data v4 (80 train clips a folder, every 4th frame).
COLLAR_NEUTRAL = {
    "bandai_namco_ccbync": {"l": (0.9598, -0.0063, -0.2806), "r": (-0.9647, -0.0620, -0.2559)},  # bandai
    "cmu_amc2bvh": {"l": (0.9240, 0.3816, 0.0258), "r": (-0.8984, 0.4385, 0.0231)},  # cmu
    "cmu_cgspeed_mb": {"l": (0.9327, 0.3572, -0.0503), "r": (-0.9495, 0.3092, -0.0527)},  # cmu
    "cmu_daz_ateliercircle": {"l": (0.9635, -0.2289, 0.1387), "r": (-0.9635, -0.2289, 0.1387)},  # daz
    "cmu_daz_papagina": {"l": (0.9635, -0.2289, 0.1387), "r": (-0.9635, -0.2289, 0.1387)},  # daz
    "cmu_fbx_daz": {"l": (0.9635, -0.2289, 0.1387), "r": (-0.9635, -0.2289, 0.1387)},  # daz
    "hdm05_ccbysa": {"l": (0.9922, 0.1247, 0.0057), "r": (-0.9969, 0.0783, 0.0061)},  # cmu
}


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


COLLAR_SKELETON = skeleton_means(COLLAR_NEUTRAL)


def collar_neutral_of(path, source):
    """The measured mean collar direction of the clip at `path` (its folder's, else its skeleton's):
    {"l": [3], "r": [3]}, or None where nothing was measured."""
    return neutral_in(COLLAR_NEUTRAL, COLLAR_SKELETON, path, source)


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
