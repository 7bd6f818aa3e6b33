"""Skeleton authors' conventions taken out in retargeting (motion.neutrals, measured by motion.conventions):
measured on a folder's motion and taken out, every normalised bone's mean is the canonical rest; the
bones' motion about it and every other joint's world orientation stay; retargeting applies each
folder's entry. Needs ../shared/mocap for the real clips."""
import numpy as np
import pytest

from edge import quat
from edge.skeleton import JOINT, NUM_JOINTS, PARENTS
from motion import conventions as cv
from motion import dataset as ds
from motion.neutrals import (CONVENTION_NEUTRAL, FEET, NORMALISED, neutral_for, normalise_conventions,
                             world_rotations)


@pytest.fixture(scope="module")
def val_frames(mocap):
    cs = ds.build(mocap, "val")
    return cv.folder_frames(cs.subset(np.arange(len(cs.names)) % 2 == 0), every=2)


WALKERS = ("bandai_namco_ccbync", "cmu_fbx_daz")      # folders of val with minutes of standing and walking
AUTHORS_CHOICE = {"pelvis_pitch_deg": -6.0, "spine": (0.0, 0.96, -0.28), "chest": (0.03, 0.99, 0.12),
                  "neck": (0.0, 0.87, -0.49), "l_ankle": -11.0, "r_ankle": 14.0}


def test_a_measured_convention_taken_out_leaves_the_rest_as_the_mean(val_frames):
    """A folder's motion given an author's conventions (its bones turned away from the rest), then measured
    (as --table does) and taken out with that entry: the spine, chest and neck read the rest direction
    exactly, the pelvis stands level and the feet sit flat at the canonical elevation."""
    checked = 0
    for folder, (rot, root) in val_frames.items():
        if folder not in WALKERS:
            continue
        authored, _ = normalise_conventions(rot, AUTHORS_CHOICE)
        root = cv.on_the_floor(authored, root)
        entry = cv.measure_entry(authored, root, every=2)
        assert abs(entry["pelvis_pitch_deg"]) > 3 and min(abs(entry["l_ankle"]), abs(entry["r_ankle"])) > 5, \
            (folder, entry)
        out, _ = normalise_conventions(authored, entry)
        after, _, _ = cv.measurer(out, cv.on_the_floor(out, root), every=2)
        world = world_rotations(out)
        for joint in NORMALISED:
            np.testing.assert_allclose(after(joint, world), [0, 1, 0], atol=1e-6, err_msg=f"{folder} {joint}")
        assert abs(after("pelvis_pitch_deg", world)) < 1.0, folder
        for ankle in FEET:
            assert abs(after(ankle, world)) < 1.5, (folder, ankle, after(ankle, world))
        checked += 1
    assert checked == len(WALKERS)


def test_taking_a_convention_out_keeps_the_motion_about_it_and_the_other_joints():
    rng = np.random.default_rng(0)
    local = quat.unroll(quat.normalize(rng.standard_normal((30, NUM_JOINTS, 4)) + [4, 0, 0, 0]))
    entry = {"pelvis_pitch_deg": 7.0, "spine": (0, 0.97, 0.243), "chest": (0.05, 0.99, -0.1), "neck": (0, 0.86, 0.51),
             "l_ankle": 12.0, "r_ankle": -9.0}
    out, _ = normalise_conventions(local, entry)
    before, after = world_rotations(local), world_rotations(out)
    turned = {0, JOINT["spine"], JOINT["chest"], JOINT["neck"], JOINT["l_ankle"], JOINT["r_ankle"],
              JOINT["l_collar"], JOINT["r_collar"], JOINT["head"]}
    for j in set(range(NUM_JOINTS)) - turned:       # every other joint keeps its world orientation
        np.testing.assert_allclose(np.abs((after[:, j] * before[:, j]).sum(-1)), 1, atol=1e-9, err_msg=str(j))
    # a bone's motion in its parent's frame is kept where the parent turns by a constant (the spine on the
    # pelvis, the feet on the shins): the angle between two frames' directions is unchanged
    for joint in ("spine", "l_ankle", "r_ankle"):
        j = JOINT[joint]
        b0, b1 = (quat.rotate(quat.mul(quat.inv(w[:, PARENTS[j]]), w[:, j]), np.broadcast_to([0.0, 0.0, 1.0], (30, 3)))
                  for w in (before, after))
        np.testing.assert_allclose((b0[1:] * b0[:-1]).sum(-1), (b1[1:] * b1[:-1]).sum(-1), atol=1e-9, err_msg=joint)
    # the collars keep their place on the chest, the head on the neck
    for c in ("l_collar", "r_collar", "head"):
        np.testing.assert_allclose(np.abs((out[:, JOINT[c]] * local[:, JOINT[c]]).sum(-1)), 1, atol=1e-9)


def test_an_unmeasured_folder_takes_the_mean_of_the_measured_ones():
    entry = neutral_for("/somewhere/else/clip.bvh")
    assert set(entry) == set(CONVENTION_NEUTRAL["cmu_fbx_daz"])
    assert entry["l_ankle"] == pytest.approx(np.mean([e["l_ankle"] for e in CONVENTION_NEUTRAL.values()]))
    assert neutral_for("x/cmu_fbx_daz/01/01_01.bvh") is CONVENTION_NEUTRAL["cmu_fbx_daz"]


@pytest.mark.parametrize("path", ["bandai_namco_ccbync/dataset-1/dataset-1_walk_normal_001.bvh",
                                  "cmu_fbx_daz/15/15_01.bvh"])
def test_retargeting_takes_each_folders_convention_out(mocap, path):
    """Retargeted, a clip's feet at flat contact point lower or higher by its folder's entry (a Bandai walk's
    were 10 deg below the canonical foot as its author placed them on average, a CMU library walk's 9 above)."""
    from motion import bvh
    from motion.retarget import resample, retarget
    if not (mocap / path).exists():
        pytest.skip(f"{path} not in this data version")
    clip = bvh.load(mocap / path)
    elevations = []
    for m in (retarget(clip, conventions=False)[0], retarget(clip)[0]):
        m = resample(m, 60.0)
        measure, _, flat = cv.measurer(m.rotations, m.root, every=1)
        assert min(flat.values()) > 30
        world = world_rotations(m.rotations)
        elevations.append(np.mean([measure(a, world) for a in FEET]))
    entry = neutral_for(path)
    assert abs(np.mean([entry[a] for a in FEET])) > 5
    assert elevations[0] - elevations[1] == pytest.approx(np.mean([entry[a] for a in FEET]), abs=1.5)


def test_evaluation_scores_on_the_ruler_asked_for(mocap):
    """edge eval's takes (and bench/sensor_sets.py --conventions in) can be scored against the clip with
    its source's conventions left in, the ruler v0.5.1's figures were published on."""
    from motion.retarget import load_motion
    from motion.synth import world_pose
    from motion.takes import from_bvh
    path = mocap / "cmu_fbx_daz/15/15_01.bvh"
    if not path.exists():
        pytest.skip("cmu_fbx_daz/15/15_01.bvh not in this data version")
    kept, taken_out = from_bvh(path, conventions=False), from_bvh(path)
    m = load_motion(path, kept.fps, conventions=False)
    assert np.allclose(kept.gt_pos, world_pose(m.rotations, m.root)[1])
    feet = [JOINT["l_toe"], JOINT["r_toe"]]
    assert np.abs(kept.gt_pos[:, feet] - taken_out.gt_pos[:, feet]).max() > 0.01
