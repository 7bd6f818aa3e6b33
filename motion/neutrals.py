"""Where each source's skeleton author put the body's joints, and how retargeting takes it out.

Three tables, each measured once per source folder on its train clips: the hands' neutral against the
forearm (HAND_NEUTRAL, `python -m motion.hands`), the collars' mean direction in the chest
(COLLAR_NEUTRAL, `python -m motion.collars`), and the rest of the body's conventions
(CONVENTION_NEUTRAL, below). The measuring modules read clips through retargeting; retargeting reads
only these tables, so neither imports the other back.

The conventions are measured by `python -m motion.conventions` (train clips, every 4th frame) on the
retargeted clips before this normalisation, in the body's chain order (each joint measured in its
parent's frame as already normalised):
- "pelvis_pitch_deg": the pelvis frame's forward lean while both feet stand flat;
- "spine", "chest", "neck": the mean direction of the bone each turns (to the chest, the neck, the
  head) in its parent's frame, over every frame;
- "l_ankle", "r_ankle": how far the foot (ankle -> toe) points above the canonical foot's elevation,
  in the world, at flat contacts (a flat foot's elevation is where the author put the ankle and toe
  joints on it: it is the same for every person standing flat).
normalise_conventions turns each by the constant rotation that takes its folder's mean to the canonical
rest (the pelvis about its hips' line, a foot about its shin's), keeping each bone's motion about it;
every other joint keeps its world orientation, but for the collars and the head, which keep their
place on their parent (KEEP_LOCAL). This module imports nothing from `motion`.
"""
from pathlib import Path

import numpy as np

from edge import quat
from edge.skeleton import JOINT, NUM_JOINTS, OFFSETS, PARENTS

# --- the hands (motion.hands measures them) and the collars (motion.collars) -------------------------

# Folder -> side -> the neutral (w, x, y, z): canonical wrist world = source hand world * neutral.
# Measured by `python -m motion.hands` on data v4 (80 train clips a folder, every 4th frame), with the
# collars about their neutral (motion.collars), which turns the upper arms' frames a little.
HAND_NEUTRAL = {
    "bandai_namco_ccbync": {"l": (0.9854, -0.0918, -0.0165, -0.1421), "r": (0.0288, 0.9876, -0.1541, -0.0074)},
    "cmu_amc2bvh": {"l": (0.9705, -0.2412, -0.0000, -0.0000), "r": (0.9403, -0.3404, 0.0000, 0.0000)},
    "cmu_cgspeed_mb": {"l": (0.9908, -0.1355, -0.0000, -0.0000), "r": (0.9671, -0.2545, 0.0000, -0.0000)},
    "cmu_daz_ateliercircle": {"l": (0.9782, -0.1386, -0.1547, -0.0098), "r": (0.9734, -0.1787, 0.1421, -0.0184)},
    "cmu_daz_papagina": {"l": (0.9750, -0.1492, -0.1590, -0.0431), "r": (0.9712, -0.1759, 0.1580, 0.0277)},
    "cmu_fbx_daz": {"l": (0.9751, -0.1612, -0.1509, -0.0186), "r": (0.9790, -0.1360, 0.1518, 0.0099)},
    "hdm05_ccbysa": {"l": (0.9786, -0.2060, 0.0002, 0.0012), "r": (0.9821, -0.1881, -0.0002, -0.0003)},
}
FOLDER_SKELETON = {"bandai_namco_ccbync": "bandai", "cmu_amc2bvh": "cmu", "cmu_cgspeed_mb": "cmu", "hdm05_ccbysa": "cmu",
                   "cmu_daz_ateliercircle": "daz", "cmu_daz_papagina": "daz", "cmu_fbx_daz": "daz"}




def skeleton_means(table):
    """{skeleton: {side: the normalised sum of its folders' entries}} of a per-folder table of unit vectors
    or quaternions: what a clip from a folder not in the table takes."""
    out = {}
    for skeleton in set(FOLDER_SKELETON.values()):
        folders = [f for f, s in FOLDER_SKELETON.items() if s == skeleton and f in table]
        if folders:
            out[skeleton] = {side: tuple(quat.normalize(np.sum([table[f][side] for f in folders], axis=0)))
                             for side in "lr"}
    return out


HAND_SKELETON = skeleton_means(HAND_NEUTRAL)


def neutral_in(table, by_skeleton, path, source):
    """The entry of a per-folder table for the clip at `path` (the nearest folder of its path in the table),
    else its skeleton's (by_skeleton, from skeleton_means), else None."""
    for part in Path(str(path)).parts[::-1]:
        if part in table:
            return table[part]
    return by_skeleton.get(source)


def hand_neutral_of(path, source):
    """The measured neutral of the clip at `path` (from its folder, else its skeleton): {"l": q, "r": q}."""
    return neutral_in(HAND_NEUTRAL, HAND_SKELETON, path, source)



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


COLLAR_SKELETON = skeleton_means(COLLAR_NEUTRAL)


def collar_neutral_of(path, source):
    """The measured mean collar direction of the clip at `path` (its folder's, else its skeleton's):
    {"l": [3], "r": [3]}, or None where nothing was measured."""
    return neutral_in(COLLAR_NEUTRAL, COLLAR_SKELETON, path, source)


# --- the pelvis, spine, chest, neck and feet (motion.conventions measures them) ----------------------

# Joint -> the child whose bone it turns, in chain order (a parent before its children).
NORMALISED = {"spine": "chest", "chest": "neck", "neck": "head"}
FEET = {"l_ankle": "l_toe", "r_ankle": "r_toe"}     # turned about the shin's x axis by their elevation
# Joints that keep their rotation on their parent: the collars (their own neutral is measured in the
# chest's frame, motion.collars) and the head (a calibrated headset reads it about its mean on the neck,
# motion.retarget.calibrated_head, so a neck at its rest holds a head that looks level).
KEEP_LOCAL = ("l_collar", "r_collar", "head")

# Measured by `python -m motion.conventions --table` on data v4 (train, every 4th frame, clip cache v7).
CONVENTION_NEUTRAL = {
    "bandai_namco_ccbync": {"pelvis_pitch_deg": -5.55, "spine": (-0.0101, 0.9991, -0.0416),
        "chest": (-0.0308, 0.9974, 0.0657),
        "neck": (-0.0385, 0.9898, 0.1370),
        "l_ankle": -10.18, "r_ankle": -10.11},
    "cmu_amc2bvh": {"pelvis_pitch_deg": 5.28, "spine": (-0.0042, 0.9794, 0.2021),
        "chest": (-0.0214, 0.9936, 0.1112),
        "neck": (0.0002, 0.9980, -0.0632),
        "l_ankle": 16.56, "r_ankle": 10.70},
    "cmu_cgspeed_mb": {"pelvis_pitch_deg": -5.33, "spine": (-0.0170, 0.9996, 0.0244),
        "chest": (-0.0103, 0.9998, -0.0186),
        "neck": (-0.0275, 0.9925, -0.1191),
        "l_ankle": 13.84, "r_ankle": 11.99},
    "cmu_daz_ateliercircle": {"pelvis_pitch_deg": 1.91, "spine": (0.0094, 0.9413, 0.3373),
        "chest": (-0.0225, 0.9752, 0.2201),
        "neck": (0.0709, 0.8632, 0.4998),
        "l_ankle": 8.08, "r_ankle": 9.22},
    "cmu_daz_papagina": {"pelvis_pitch_deg": 4.80, "spine": (-0.0172, 0.9991, 0.0392),
        "chest": (-0.0140, 0.9949, -0.1001),
        "neck": (-0.0038, 0.9335, 0.3586),
        "l_ankle": 12.44, "r_ankle": 11.84},
    "cmu_fbx_daz": {"pelvis_pitch_deg": 6.48, "spine": (-0.0029, 0.9703, 0.2418),
        "chest": (-0.0161, 0.9893, 0.1450),
        "neck": (0.0150, 0.8581, 0.5133),
        "l_ankle": 9.04, "r_ankle": 10.28},
    "hdm05_ccbysa": {"pelvis_pitch_deg": -3.03, "spine": (-0.0340, 0.9955, 0.0888),
        "chest": (-0.0064, 0.9958, 0.0916),
        "neck": (0.0205, 0.9978, 0.0627),
        "l_ankle": 3.64, "r_ankle": 4.13},
}


def rest_direction(child):
    v = OFFSETS[JOINT[child]]
    return v / np.linalg.norm(v)


def world_rotations(local):
    """Local joint rotations [T,J,4] -> world [T,J,4] (FK of the rotations alone)."""
    world = np.empty_like(local)
    world[:, 0] = local[:, 0]
    for j in range(1, NUM_JOINTS):
        world[:, j] = quat.mul(world[:, PARENTS[j]], local[:, j])
    return world


def local_rotations(world):
    local = np.empty_like(world)
    local[:, 0] = world[:, 0]
    for j in range(1, NUM_JOINTS):
        local[:, j] = quat.mul(quat.inv(world[:, PARENTS[j]]), world[:, j])
    return local


def about_x(deg):
    """A rotation about a frame's x axis (the hips' line, a shin's): + leans up forward, points forward down."""
    return quat.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.radians(deg))


def foot_elevation_deg(world, ankle):
    """How far the foot ankle -> toe points above the horizontal [T] (degrees; the rest foot: -28.3)."""
    d = quat.rotate(world[:, JOINT[ankle]], np.broadcast_to(rest_direction(FEET[ankle]), world.shape[:-2] + (3,)))
    return np.degrees(np.arcsin(np.clip(d[..., 1], -1, 1)))


REST_FOOT_ELEVATION_DEG = float(np.degrees(np.arcsin(rest_direction("l_toe")[1])))


def bone_in_parent(world, joint):
    """The bone `joint` -> its normalised child as a unit direction in the parent's frame [T,3]."""
    local = quat.mul(quat.inv(world[:, PARENTS[JOINT[joint]]]), world[:, JOINT[joint]])
    return quat.rotate(local, np.broadcast_to(rest_direction(NORMALISED[joint]), local.shape[:-1] + (3,)))


def normalise_conventions(local, neutral, measure=None):
    """Local rotations [T,J,4] of one source -> the same motion with its conventions taken out (module
    docstring). `neutral`: the folder's table entry. With `measure` (a function of (name, world) that
    returns the entry's value from this motion, as it stands with its parents already normalised),
    each value is measured before it is applied: what motion.conventions does to build the table.
    -> (local rotations, the entry used)."""
    world = world_rotations(np.asarray(local, dtype=np.float64))
    kept = {c: quat.mul(quat.inv(world[:, PARENTS[JOINT[c]]]), world[:, JOINT[c]]) for c in KEEP_LOCAL}
    used = {}
    pitch = measure("pelvis_pitch_deg", world) if measure else neutral.get("pelvis_pitch_deg")
    if pitch is not None:
        world[:, 0] = quat.mul(world[:, 0], about_x(-pitch))
        used["pelvis_pitch_deg"] = float(pitch)
    for joint, child in NORMALISED.items():
        mean = measure(joint, world) if measure else neutral.get(joint)
        if mean is None:
            continue
        j, p = JOINT[joint], PARENTS[JOINT[joint]]
        swing = quat.between(np.asarray(mean, dtype=np.float64), rest_direction(child))
        now = quat.mul(quat.inv(world[:, p]), world[:, j])
        world[:, j] = quat.mul(world[:, p], quat.mul(np.broadcast_to(swing, now.shape), now))
        used[joint] = tuple(float(x) for x in mean)
    for ankle in FEET:
        above = measure(ankle, world) if measure else neutral.get(ankle)
        if above is None:
            continue
        j, p = JOINT[ankle], PARENTS[JOINT[ankle]]
        world[:, j] = quat.mul(world[:, p], quat.mul(about_x(above)[None], quat.mul(quat.inv(world[:, p]), world[:, j])))
        used[ankle] = float(above)
    for c, keep in kept.items():
        world[:, JOINT[c]] = quat.mul(world[:, PARENTS[JOINT[c]]], keep)
    return quat.normalize(local_rotations(world)), used


def neutral_for(path, table=None):
    """The table entry of the clip at `path` (the nearest of its path's folders in the table), else the
    mean of the table's entries (a source not measured), else {} (nothing to take out)."""
    table = CONVENTION_NEUTRAL if table is None else table
    for part in Path(str(path)).parts[::-1]:
        if part in table:
            return table[part]
    if not table:
        return {}
    entries = list(table.values())
    mean = {"pelvis_pitch_deg": float(np.mean([e["pelvis_pitch_deg"] for e in entries]))}
    for joint in NORMALISED:
        v = np.sum([e[joint] for e in entries], axis=0)
        mean[joint] = tuple(v / np.linalg.norm(v))
    for ankle in FEET:
        mean[ankle] = float(np.mean([e[ankle] for e in entries]))
    return mean
