"""Where each source's skeleton author put the body's joints, and how retargeting takes it out.

Measured once per source folder by `python -m motion.conventions` (train clips, every 4th frame) on the
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
place on their parent (KEEP_LOCAL). This module imports nothing from `motion`, so retargeting and
the measurement both read it.
"""
from pathlib import Path

import numpy as np

from edge import quat
from edge.skeleton import JOINT, NUM_JOINTS, OFFSETS, PARENTS

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
