"""The hands' and the head's own orientation in retargeting: each source's neutral hand and head,
measured once, and the spread of the hands' roll and bend against the forearm and of the head against
the neck.

The sources' hand frames follow their own conventions (Bandai's zero pose is not a T-pose; Daz's
hand axes lean off the forearm), so no bind pose says where a neutral hand is. The neutral is
measured instead: over a source folder's train clips, the mean rotation between the source's hand and
the canonical forearm. Retargeting sets the canonical wrist to the source hand's world rotation
times that neutral, so a hand held in line with its forearm, at the folder's average roll, has the
identity local rotation, as in the canonical T-pose. The head needs no table: retargeting takes the
source head's turn on the neck about its own mean over the clip (motion.retarget.calibrated_head, a
calibrated headset), which no constant offset of a source's head frame changes; this module reports its
spread.

    python -m motion.hands [--data ../shared/mocap] [--clips 80]

prints, per folder and side, the measured neutral (the HAND_NEUTRAL table below) and the spread of
roll (about the forearm) and bend (the hand's long axis off the forearm's) beside human ranges.
"""
import argparse
import collections
from pathlib import Path

import numpy as np

from edge import quat
from motion.neutrals import HAND_NEUTRAL  # noqa: F401  (the table this module measures)
from motion.retarget import hand_world, head_world


# Human ranges against the forearm (degrees): pronation/supination about it, and the wrist's bend
# (flexion 0-80, extension 0-70, radial 20, ulnar 30; e.g. the AAOS normal ranges).
HUMAN_ROLL_DEG = 90.0
HUMAN_BEND_DEG = 80.0
# The head on the neck: nodding (flexion 50, extension 60) and turning (70 each way) (AAOS normal ranges).
HUMAN_NOD_DEG = 60.0
HUMAN_TURN_DEG = 70.0


def train_clips_by_folder(root, clips, seed=0):
    """{folder: up to `clips` of its train clips, drawn at random} of the mocap folder `root`: what the
    neutrals are measured on."""
    from motion.dataset import read_manifest
    by_folder = collections.defaultdict(list)
    for r in read_manifest(root):
        if r["split"] == "train":
            by_folder[r["file"].split("/")[0]].append(r["file"])
    rng = np.random.default_rng(seed)
    return {folder: rng.choice(files, min(clips, len(files)), replace=False) for folder, files in sorted(by_folder.items())}


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
    """{folder: {side: (neutral quat, [n] roll deg, [n] bend deg), "head": ([n] nod deg, [n] turn deg) of the
    calibrated head on the neck}} over up to `clips` train clips a folder."""
    from motion import bvh
    from motion.retarget import calibrated_head, detect_source, retarget
    from edge.skeleton import JOINT, fk
    out = {}
    for folder, files in train_clips_by_folder(root, clips, seed).items():
        pairs = {"l": [], "r": [], "head": []}
        skeleton = None
        for f in files:
            clip = bvh.load(Path(root) / f)
            skeleton = detect_source(clip)
            motion, _ = retarget(clip, skeleton, hands=False)
            world, _ = fk(quat.to_matrix(motion.rotations[::step]), motion.root[::step])
            for side in "lr":
                hand = quat.to_matrix(hand_world(clip, skeleton, side)[::step])
                pairs[side].append((hand, world[:, JOINT[f"{side}_elbow"]]))
            neck = quat.from_matrix(world[:, JOINT["neck"]])
            head = calibrated_head(neck, head_world(clip, skeleton)[::step])
            pairs["head"].append(quat.mul(quat.inv(neck), head))
        out[folder] = {"skeleton": skeleton}
        for side in "lr":
            hand = np.concatenate([h for h, _ in pairs[side]])
            forearm = np.concatenate([f for _, f in pairs[side]])
            neutral = mean_rotation(np.swapaxes(hand, -1, -2) @ forearm)
            local = quat.from_matrix(np.swapaxes(forearm, -1, -2) @ hand @ neutral)
            out[folder][side] = (quat.from_matrix(neutral),) + roll_and_bend(local)
        out[folder]["head"] = nod_and_turn(np.concatenate(pairs["head"]))
    return out


def measured_from_command_line(doc, measure):
    """`python -m motion.hands` and `motion.collars`: parse --data and --clips, and measure on them."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--clips", type=int, default=80)
    a = ap.parse_args()
    return measure(a.data, a.clips)


def main():
    m = measured_from_command_line(__doc__, measure)
    print(f"hands against the forearm, per folder (p5 / p50 / p95 of |roll| and bend, degrees; human: roll up to "
          f"{HUMAN_ROLL_DEG:.0f}, bend up to {HUMAN_BEND_DEG:.0f})")
    for folder, d in m.items():
        for side in "lr":
            _, roll, bend = d[side]
            r, b = np.percentile(np.abs(roll), [5, 50, 95]), np.percentile(bend, [5, 50, 95])
            real = "roll and bend" if b[2] > 10 else "roll only (the hand stays in line with the forearm)"
            print(f"  {folder:24s} {side}  roll {r[0]:5.1f} {r[1]:5.1f} {r[2]:5.1f}   bend {b[0]:5.1f} {b[1]:5.1f} "
                  f"{b[2]:5.1f}   {real}")
    print(f"\nthe calibrated head against the neck, per folder (p5 / p50 / p95 of |nod| and |turn|, degrees; human: nod up to "
          f"{HUMAN_NOD_DEG:.0f}, turn up to {HUMAN_TURN_DEG:.0f})")
    for folder, d in m.items():
        nod, turn = d["head"]
        n, t = np.percentile(np.abs(nod), [5, 50, 95]), np.percentile(np.abs(turn), [5, 50, 95])
        print(f"  {folder:24s}    nod {n[0]:5.1f} {n[1]:5.1f} {n[2]:5.1f}   turn {t[0]:5.1f} {t[1]:5.1f} {t[2]:5.1f}")
    print("\nHAND_NEUTRAL = {")
    for folder, d in m.items():
        q = {s: ", ".join(f"{v:.4f}" for v in d[s][0]) for s in "lr"}
        print(f'    "{folder}": {{"l": ({q["l"]}), "r": ({q["r"]})}},  # {d["skeleton"]}')
    print("}")


if __name__ == "__main__":
    main()
