"""Skeleton authors' conventions beyond the collars, measured per source folder (motion.neutrals).

Retargeting gives each canonical bone its source bone's direction. Where the source author put a joint
is a convention, not motion: a spine joint placed in front of the hips tilts the pelvis frame, a toe
joint at the ball of the foot rather than lower down points the foot up. The model cannot tell sources
apart, so it learns their average (motion.collars found the collars' one: 8.5 cm at the shoulder).

    python -m motion.conventions [--data ../shared/mocap] [--every 4] [--json out/conventions.json] [--table]

measures, on each folder's train clips as the cache holds them, the pelvis frame's lean while standing
and the mean direction of the spine, chest, neck and feet (feet at flat contacts: ankle and toe on the
floor and still) in their parents' frames, against the canonical rest, in degrees and in cm at the
bone's end. --table measures them in chain order as motion.neutrals takes them out (each with its
parents already normalised) and prints CONVENTION_NEUTRAL; on clips retargeted with the table in place
every entry reads the rest (what tests/test_conventions.py checks).
"""
import argparse
import json
from pathlib import Path

import numpy as np

from edge import quat
from edge.skeleton import JOINT, OFFSETS, TOE_HEIGHT
from motion.neutrals import (CONVENTION_NEUTRAL, FEET, NORMALISED, REST_FOOT_ELEVATION_DEG, bone_in_parent,
                             foot_elevation_deg, normalise_conventions, rest_direction, world_rotations)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def flat_contacts(pos, fps=60.0, height=0.06, speed=0.15):
    """Frames where a foot stands flat: its toe within `height` of the floor, its ankle within the
    foot's rest height of that, and both slower than `speed` m/s -> {"l_ankle": [F] bool, "r_ankle": ...}."""
    out = {}
    for side in "lr":
        a, t = pos[:, JOINT[f"{side}_ankle"]], pos[:, JOINT[f"{side}_toe"]]
        va = np.linalg.norm(np.gradient(a, axis=0), axis=-1) * fps
        vt = np.linalg.norm(np.gradient(t, axis=0), axis=-1) * fps
        low = (t[:, 1] < TOE_HEIGHT + height) & (a[:, 1] < TOE_HEIGHT + height + abs(OFFSETS[JOINT[f"{side}_toe"], 1]) + 0.03)
        out[f"{side}_ankle"] = low & (va < speed) & (vt < speed)
    return out


def pelvis_pitch_deg(pelvis_world):
    """How far the pelvis frame's up axis leans forward of vertical [F] (degrees, + forward), in the
    pelvis's own heading (its hips' line, horizontal)."""
    up = quat.rotate(pelvis_world, np.broadcast_to([0.0, 1.0, 0.0], pelvis_world.shape[:-1] + (3,)))
    side = quat.rotate(pelvis_world, np.broadcast_to([1.0, 0.0, 0.0], pelvis_world.shape[:-1] + (3,))).copy()
    side[..., 1] = 0
    forward = _unit(np.cross(_unit(side), [0.0, 1.0, 0.0]))
    return np.degrees(np.arctan2((up * forward).sum(-1), up[..., 1]))


def folder_of(name, folders):
    """The folder among `folders` that a clip's path is in, or "unknown"."""
    for part in Path(str(name)).parts:
        if part in folders:
            return part
    return "unknown"


def folder_frames(cs, every=4):
    """{folder: (rotations [F,J,4] float64, root [F,3])} of a ClipSet's clips, every `every`-th frame."""
    from motion.dataset import FOLDER_GROUP
    folders = np.array([folder_of(n, FOLDER_GROUP) for n in cs.names])
    out = {}
    for folder in sorted(set(folders)):
        frames = np.concatenate([np.arange(s, s + n, every) for s, n, f in zip(cs.starts, cs.lengths(), folders,
                                                                               strict=True) if f == folder])
        out[folder] = (cs.rotations[frames].astype(np.float64), cs.root[frames].astype(np.float64))
    return out


def measurer(rot, root, every):
    """A `measure` for normalise_conventions over frames (rot, root): each entry's value as the motion
    stands when it is asked (the pelvis's mean lean while standing, a bone's mean direction)."""
    from motion.synth import world_pose
    _, pos = world_pose(rot, root)
    flat = flat_contacts(pos, 60.0 / every)
    standing = flat["l_ankle"] & flat["r_ankle"]

    def measure(name, world):
        if name == "pelvis_pitch_deg":
            return float(np.mean(pelvis_pitch_deg(world[standing, 0])))
        if name in flat:        # the foot's elevation above the canonical one, at flat contacts
            return float(np.mean(foot_elevation_deg(world[flat[name]], name)) - REST_FOOT_ELEVATION_DEG)
        return tuple(_unit(bone_in_parent(world, name).mean(0)))
    return measure, int(standing.sum()), {k: int(v.sum()) for k, v in flat.items()}


def on_the_floor(rot, root):
    """The root moved so the lower toe's 5th percentile is at the rest toe height (motion.retarget's
    place_on_floor, over the frames given)."""
    from motion.retarget import Motion, place_on_floor
    m = Motion(rot, root.copy(), 60.0)
    place_on_floor(m)
    return m.root


def measure_entry(rot, root, every, rounds=2):
    """One folder's entry, measured on its motion without it: in chain order (each joint with its parents
    already normalised), then `rounds` - 1 more times for the pelvis and feet, whose frames (standing, a
    foot flat) move when their own convention is taken out and the motion put back on the floor."""
    measure, _, _ = measurer(rot, root, every)
    _, entry = normalise_conventions(rot, {}, measure)
    for _ in range(rounds - 1):
        out, _ = normalise_conventions(rot, entry)
        again, _, _ = measurer(out, on_the_floor(out, root), every)
        world = world_rotations(out)
        fixed = {name: entry[name] + again(name, world) for name in ("pelvis_pitch_deg",) + tuple(FEET)}  # one axis each

        def with_fixed(name, w, fixed=fixed):
            return fixed[name] if name in fixed else measure(name, w)
        # the spine, chest and neck again, in the pelvis's new frame
        _, entry = normalise_conventions(rot, {}, with_fixed)
    return entry


def table(cs, every=4):
    """CONVENTION_NEUTRAL measured on a ClipSet retargeted without it: {folder: entry}."""
    return {folder: measure_entry(rot, root, every) for folder, (rot, root) in folder_frames(cs, every).items()}


def deviations(cs, every=4):
    """{folder: {entry: (degrees from the rest, cm at the bone's end)}} of a ClipSet as it is (each bone
    in its parent's frame as retargeting left it; the pelvis's lean while standing)."""
    out = {}
    for folder, (rot, root) in folder_frames(cs, every).items():
        measure, standing, flat = measurer(rot, root, every)
        world = world_rotations(rot)
        out[folder] = {"pelvis_pitch_deg": (measure("pelvis_pitch_deg", world), np.nan), "standing_frames": standing}
        for joint, child in NORMALISED.items():
            mean, rest = np.asarray(measure(joint, world)), rest_direction(child)
            out[folder][joint] = (float(np.degrees(np.arccos(np.clip(mean @ rest, -1, 1)))),
                                  float(np.linalg.norm(mean - rest) * np.linalg.norm(OFFSETS[JOINT[child]]) * 100))
        for ankle, toe in FEET.items():
            above = measure(ankle, world)
            out[folder][ankle] = (above, float(2 * np.sin(np.radians(abs(above)) / 2) * np.linalg.norm(OFFSETS[JOINT[toe]]) * 100))
    return out


def main(argv=None):
    from motion import dataset as ds
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--json")
    ap.add_argument("--table", action="store_true", help="measure CONVENTION_NEUTRAL (on clips retargeted without it)")
    a = ap.parse_args(argv)
    cs = ds.build(a.data, "train")
    if a.table:
        t = table(cs, a.every)
        print("CONVENTION_NEUTRAL = {")
        for folder, e in t.items():
            parts = [f'"pelvis_pitch_deg": {e["pelvis_pitch_deg"]:.2f}'] + \
                [f'"{j}": ({", ".join(f"{v:.4f}" for v in e[j])})' for j in NORMALISED] + \
                [f'"{j}": {e[j]:.2f}' for j in FEET]
            print(f'    "{folder}": {{{", ".join(parts)}}},')
        print("}")
        return
    dev = deviations(cs, a.every)
    print(f"each source against the canonical rest, train clips{' (normalised)' if CONVENTION_NEUTRAL else ''}: "
          "the pelvis's forward lean standing (deg); each bone's mean in its parent's frame (deg, cm at its end)")
    print(f"{'folder':24s} {'pelvis':>7s} | " + " | ".join(f"{j:>13s}" for j in NORMALISED) + " | "
          + " | ".join(f"{j + ' (above)':>13s}" for j in FEET))
    for folder, d in dev.items():
        print(f"{folder:24s} {d['pelvis_pitch_deg'][0]:+7.1f} | "
              + " | ".join(f"{d[j][0]:+5.1f} {d[j][1]:4.1f} cm" for j in list(NORMALISED) + list(FEET)))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(dev, indent=2) + "\n")


if __name__ == "__main__":
    main()
