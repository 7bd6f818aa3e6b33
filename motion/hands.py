"""The hands' and the head's own orientation in retargeting: each source's neutral hand and head,
measured once, and the spread of the hands' roll and bend against the forearm and of the head against
the neck.

The sources' hand frames follow their own conventions (Bandai's zero pose is not a T-pose; Daz's
hand axes lean off the forearm), so no bind pose says where a neutral hand is. The neutral is
measured instead: over a source folder's train clips, the mean rotation between the source's hand and
the canonical forearm. Retargeting sets the canonical wrist to the source hand's world rotation
times that neutral, so a hand held in line with its forearm, at the folder's average roll, has the
identity local rotation, as in the canonical T-pose. The head likewise: the canonical head is the source
head's world rotation times the folder's neutral (the mean rotation between the source's head and the
canonical neck), so the synthesised headset nods and turns on the neck as the person's head did.

    python -m motion.hands [--data ../shared/mocap] [--clips 80]

prints, per folder and side, the measured neutral (the HAND_NEUTRAL table below) and the spread of
roll (about the forearm) and bend (the hand's long axis off the forearm's) beside human ranges.
"""
import argparse
import collections
from pathlib import Path

import numpy as np

from edge import quat

# Folder -> side -> the neutral (w, x, y, z): canonical wrist world = source hand world * neutral.
# Measured by `python -m motion.hands` on data v4 (80 train clips a folder, every 4th frame).
HAND_NEUTRAL = {
    "bandai_namco_ccbync": {"l": (0.9753, -0.1701, -0.0064, -0.1409), "r": (0.1056, 0.9826, -0.1519, -0.0186)},
    "cmu_amc2bvh": {"l": (0.9746, -0.2238, -0.0000, 0.0000), "r": (0.9455, -0.3255, 0.0000, -0.0000)},
    "cmu_cgspeed_mb": {"l": (0.9943, -0.1067, -0.0000, -0.0000), "r": (0.9708, -0.2398, 0.0000, -0.0000)},
    "cmu_daz_ateliercircle": {"l": (0.9829, -0.0991, -0.1554, -0.0038), "r": (0.9770, -0.1583, 0.1412, -0.0210)},
    "cmu_daz_papagina": {"l": (0.9802, -0.1103, -0.1601, -0.0371), "r": (0.9782, -0.1320, 0.1591, 0.0208)},
    "cmu_fbx_daz": {"l": (0.9811, -0.1195, -0.1518, -0.0122), "r": (0.9838, -0.0945, 0.1520, 0.0036)},
    "hdm05_ccbysa": {"l": (0.9825, -0.1862, 0.0002, 0.0012), "r": (0.9843, -0.1768, -0.0002, -0.0003)},
}
# Folder -> the head's neutral (w, x, y, z): canonical head world = source head world * neutral.
# Measured by `python -m motion.hands --clips 60` on data v4 (every 4th frame). The head on the neck, p50 / p95:
# nod 4-17 / 16-40 deg, turn 6-22 / 31-53 deg (Bandai the stillest, Daz the most nodding).
HEAD_NEUTRAL = {
    "bandai_namco_ccbync": (0.5091, -0.4947, -0.4800, -0.5155),
    "cmu_amc2bvh": (0.9922, -0.1187, 0.0236, -0.0306),
    "cmu_cgspeed_mb": (0.9955, -0.0922, -0.0040, -0.0214),
    "cmu_daz_ateliercircle": (0.9874, 0.1501, 0.0396, -0.0295),
    "cmu_daz_papagina": (0.9782, 0.1942, 0.0612, -0.0416),
    "cmu_fbx_daz": (0.9784, 0.1683, 0.0713, -0.0964),
    "hdm05_ccbysa": (0.9988, -0.0310, 0.0348, -0.0136),
}
FOLDER_SKELETON = {"bandai_namco_ccbync": "bandai", "cmu_amc2bvh": "cmu", "cmu_cgspeed_mb": "cmu", "hdm05_ccbysa": "cmu",
                   "cmu_daz_ateliercircle": "daz", "cmu_daz_papagina": "daz", "cmu_fbx_daz": "daz"}


def _skeleton_means():
    """A clip from a folder not in the table takes its skeleton's neutral: the mean of that skeleton's folders."""
    out = {}
    for skeleton in set(FOLDER_SKELETON.values()):
        folders = [f for f, s in FOLDER_SKELETON.items() if s == skeleton]
        out[skeleton] = {side: tuple(quat.normalize(np.sum([HAND_NEUTRAL[f][side] for f in folders], axis=0)))
                         for side in "lr"}
    return out


HAND_SKELETON = _skeleton_means()


def head_neutral_of(path, source):
    """The measured head neutral of the clip at `path` (from its folder, else its skeleton's mean), or None."""
    for part in Path(str(path)).parts[::-1]:
        if part in HEAD_NEUTRAL:
            return HEAD_NEUTRAL[part]
    folders = [f for f, s in FOLDER_SKELETON.items() if s == source and f in HEAD_NEUTRAL]
    return tuple(quat.normalize(np.sum([HEAD_NEUTRAL[f] for f in folders], axis=0))) if folders else None


def head_world(clip, source):
    """The source head's world rotation [T,4]."""
    from motion.retarget import SOURCE_MAPS
    world_rot, _ = clip.world()
    return world_rot[:, clip.index(SOURCE_MAPS[source]["head"])]

# Human ranges against the forearm (degrees): pronation/supination about it, and the wrist's bend
# (flexion 0-80, extension 0-70, radial 20, ulnar 30; e.g. the AAOS normal ranges).
HUMAN_ROLL_DEG = 90.0
HUMAN_BEND_DEG = 80.0
# The head on the neck: nodding (flexion 50, extension 60) and turning (70 each way) (AAOS normal ranges).
HUMAN_NOD_DEG = 60.0
HUMAN_TURN_DEG = 70.0


def neutral_of(path, source):
    """The measured neutral of the clip at `path` (from its folder, else its skeleton): {"l": q, "r": q}."""
    for part in Path(str(path)).parts[::-1]:
        if part in HAND_NEUTRAL:
            return HAND_NEUTRAL[part]
    return HAND_SKELETON.get(source)


def hand_world(clip, source, side):
    """The source hand's world rotation [T,4] of one side ("l" or "r")."""
    from motion.retarget import SOURCE_MAPS
    world_rot, _ = clip.world()
    return world_rot[:, clip.index(SOURCE_MAPS[source][f"{side}_wrist"])]


def mean_rotation(m):
    """Chordal L2 mean of rotation matrices [n,3,3]: the nearest rotation to their average."""
    u, _, vt = np.linalg.svd(m.mean(0))
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] *= -1
    return u @ vt


def roll_and_bend(local):
    """A hand's local rotation against its forearm [...,4] -> (roll about the forearm, bend of the hand's
    axis off the forearm's), degrees. The canonical forearm runs along x (+x left, -x right)."""
    x = quat.rotate(local, np.broadcast_to([1.0, 0.0, 0.0], local.shape[:-1] + (3,)))
    bend = np.degrees(np.arccos(np.clip(x[..., 0], -1.0, 1.0)))
    roll = np.degrees(2 * np.arctan2(local[..., 1], local[..., 0]))     # swing-twist: the twist about x
    return (roll + 180.0) % 360.0 - 180.0, bend


def nod_and_turn(local):
    """The head's local rotation against the neck [...,4] -> (nod: the face's pitch, turn: its yaw about
    the neck), degrees. The canonical face looks along +z, the neck runs along +y."""
    z = quat.rotate(local, np.broadcast_to([0.0, 0.0, 1.0], local.shape[:-1] + (3,)))
    nod = np.degrees(np.arcsin(np.clip(-z[..., 1], -1.0, 1.0)))
    turn = np.degrees(np.arctan2(z[..., 0], z[..., 2]))
    return nod, turn


def measure(root, clips=80, seed=0, step=4):
    """{folder: {side: (neutral quat, [n] roll deg, [n] bend deg), "head": (neutral quat, [n] nod deg,
    [n] turn deg)}} over up to `clips` train clips a folder."""
    from motion import bvh
    from motion.dataset import read_manifest
    from motion.retarget import detect_source, retarget
    from edge.skeleton import JOINT, fk
    by_folder = collections.defaultdict(list)
    for r in read_manifest(root):
        if r["split"] == "train":
            by_folder[r["file"].split("/")[0]].append(r["file"])
    rng = np.random.default_rng(seed)
    out = {}
    for folder, files in sorted(by_folder.items()):
        pairs = {"l": [], "r": [], "head": []}
        skeleton = None
        for f in rng.choice(files, min(clips, len(files)), replace=False):
            clip = bvh.load(Path(root) / f)
            skeleton = detect_source(clip)
            motion, _ = retarget(clip, skeleton, hands=False)
            world, _ = fk(quat.to_matrix(motion.rotations[::step]), motion.root[::step])
            for side in "lr":
                hand = quat.to_matrix(hand_world(clip, skeleton, side)[::step])
                pairs[side].append((hand, world[:, JOINT[f"{side}_elbow"]]))
            pairs["head"].append((quat.to_matrix(head_world(clip, skeleton)[::step]), world[:, JOINT["neck"]]))
        out[folder] = {"skeleton": skeleton}
        for side in "lr":
            hand = np.concatenate([h for h, _ in pairs[side]])
            forearm = np.concatenate([f for _, f in pairs[side]])
            neutral = mean_rotation(np.swapaxes(hand, -1, -2) @ forearm)
            local = quat.from_matrix(np.swapaxes(forearm, -1, -2) @ hand @ neutral)
            out[folder][side] = (quat.from_matrix(neutral),) + roll_and_bend(local)
        head = np.concatenate([h for h, _ in pairs["head"]])
        neck = np.concatenate([n for _, n in pairs["head"]])
        neutral = mean_rotation(np.swapaxes(head, -1, -2) @ neck)
        local = quat.from_matrix(np.swapaxes(neck, -1, -2) @ head @ neutral)
        out[folder]["head"] = (quat.from_matrix(neutral),) + nod_and_turn(local)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--clips", type=int, default=80)
    a = ap.parse_args()
    m = measure(a.data, a.clips)
    print(f"hands against the forearm, per folder (p5 / p50 / p95 of |roll| and bend, degrees; human: roll up to "
          f"{HUMAN_ROLL_DEG:.0f}, bend up to {HUMAN_BEND_DEG:.0f})")
    for folder, d in m.items():
        for side in "lr":
            _, roll, bend = d[side]
            r, b = np.percentile(np.abs(roll), [5, 50, 95]), np.percentile(bend, [5, 50, 95])
            real = "roll and bend" if b[2] > 10 else "roll only (the hand stays in line with the forearm)"
            print(f"  {folder:24s} {side}  roll {r[0]:5.1f} {r[1]:5.1f} {r[2]:5.1f}   bend {b[0]:5.1f} {b[1]:5.1f} "
                  f"{b[2]:5.1f}   {real}")
    print(f"\nthe head against the neck, per folder (p5 / p50 / p95 of |nod| and |turn|, degrees; human: nod up to "
          f"{HUMAN_NOD_DEG:.0f}, turn up to {HUMAN_TURN_DEG:.0f})")
    for folder, d in m.items():
        _, nod, turn = d["head"]
        n, t = np.percentile(np.abs(nod), [5, 50, 95]), np.percentile(np.abs(turn), [5, 50, 95])
        print(f"  {folder:24s}    nod {n[0]:5.1f} {n[1]:5.1f} {n[2]:5.1f}   turn {t[0]:5.1f} {t[1]:5.1f} {t[2]:5.1f}")
    print("\nHEAD_NEUTRAL = {")
    for folder, d in m.items():
        print(f'    "{folder}": ({", ".join(f"{v:.4f}" for v in d["head"][0])}),  # {d["skeleton"]}')
    print("}")
    print("\nHAND_NEUTRAL = {")
    for folder, d in m.items():
        q = {s: ", ".join(f"{v:.4f}" for v in d[s][0]) for s in "lr"}
        print(f'    "{folder}": {{"l": ({q["l"]}), "r": ({q["r"]})}},  # {d["skeleton"]}')
    print("}")


if __name__ == "__main__":
    main()
