"""Retargeting onto the canonical skeleton, resampling and FK."""
import numpy as np
import pytest

from edge import quat
from motion import bvh
from motion.retarget import LIMB_BONES, direction_errors_deg, resample, retarget
from edge.skeleton import JOINT, NUM_JOINTS, OFFSETS, PARENTS, REST, fk
from tests.conftest import SKELETON_CLIPS


def test_fk_of_identity_rotations_is_the_rest_pose():
    rot = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    _, pos = fk(rot, np.zeros(3))
    assert np.allclose(pos, REST)


def test_fk_keeps_bone_lengths_under_any_rotation():
    q = quat.normalize(np.random.default_rng(0).standard_normal((10, NUM_JOINTS, 4)))
    _, pos = fk(quat.to_matrix(q), np.zeros((10, 3)))
    lengths = np.linalg.norm(pos[:, 1:] - pos[:, PARENTS[1:]], axis=-1)
    assert np.allclose(lengths, np.linalg.norm(OFFSETS[1:], axis=-1))


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_limb_directions_match_the_source_within_two_degrees(mocap, source):
    clip = bvh.load(mocap / SKELETON_CLIPS[source])
    motion, src = retarget(clip, conventions=False)
    err = direction_errors_deg(motion, src)
    assert err[:, LIMB_BONES].mean() < 2.0
    # Spine and neck chain also follow the source exactly.
    spine = [JOINT[n] - 1 for n in ("chest", "neck", "head")]
    assert err[:, spine].mean() < 2.0
    # With the source's conventions taken out (motion.neutrals) the arms and legs still do, all but the foot
    motion, src = retarget(clip)
    legs_and_arms = [b for b in LIMB_BONES if b not in (JOINT["l_toe"] - 1, JOINT["r_toe"] - 1)]
    assert direction_errors_deg(motion, src)[:, legs_and_arms].mean() < 2.0


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_retargeted_clip_stands_on_the_floor(mocap, source):
    motion, _ = retarget(bvh.load(mocap / SKELETON_CLIPS[source]))
    _, pos = fk(quat.to_matrix(motion.rotations), motion.root)
    lowest = pos[:, [JOINT["l_toe"], JOINT["r_toe"]], 1].min(1)
    assert abs(np.percentile(lowest, 5) - 0.02) < 1e-6
    assert 1.5 < np.median(pos[:, JOINT["head"], 1]) + 0.1 < 1.9


def test_resample_30_to_60_keeps_duration_and_interpolates():
    from motion.retarget import Motion
    T = 31
    angles = np.linspace(0, np.pi / 2, T)
    rot = np.tile([1.0, 0, 0, 0], (T, NUM_JOINTS, 1))
    rot[:, JOINT["l_knee"]] = quat.from_axis_angle(np.array([1.0, 0, 0]), angles)
    root = np.stack([np.linspace(0, 1, T), np.ones(T), np.zeros(T)], -1)
    out = resample(Motion(rot, root, 30.0), 60.0)
    assert out.frames == 61 and out.fps == 60.0
    assert np.allclose(out.root[1, 0], 1 / 60)
    mid = quat.angle(out.rotations[1, JOINT["l_knee"]])
    assert np.isclose(mid, np.pi / 2 / 60)


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_retargeted_wrists_take_the_source_hands_own_turn_near_their_neutral(mocap, source):
    """The wrists follow the source hands (motion.hands): near identity on average (the measured
    neutral), and moving through the clip, where a leaf copying its forearm would never turn."""
    clip = bvh.load(mocap / SKELETON_CLIPS[source])
    wrists = [JOINT["l_wrist"], JOINT["r_wrist"]]
    motion, _ = retarget(clip)
    turn = np.degrees(quat.angle(motion.rotations[:, wrists]))
    assert np.median(turn) < 30.0
    assert (np.percentile(turn, 95, axis=0) - np.percentile(turn, 5, axis=0)).min() > 8.0
    forearm, _ = retarget(clip, hands=False)
    assert np.allclose(quat.angle(forearm.rotations[:, wrists]), 0.0, atol=1e-6)


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_retargeted_head_nods_and_turns_on_the_neck_near_its_neutral(mocap, source):
    """The head follows the source head's turn on the neck about its mean over the clip (a calibrated
    headset; motion.retarget.calibrated_head), so the synthesised headset nods and turns on the neck as
    the person's did, where a leaf copying the neck would never turn (the headset would then say exactly
    where the neck points, which no person's does)."""
    clip = bvh.load(mocap / SKELETON_CLIPS[source])
    motion, _ = retarget(clip)
    head = motion.rotations[:, JOINT["head"]]
    turn = np.degrees(quat.angle(head))
    assert np.median(turn) < 30.0
    assert np.percentile(turn, 95) - np.percentile(turn, 5) > 3.0
    mean = quat.normalize(np.where((head @ head[0])[:, None] < 0, -head, head).mean(0))
    assert np.degrees(quat.angle(mean)) < 1.0     # calibrated: on the neck it turns about the identity
    neck, _ = retarget(clip, hands=False)
    assert np.allclose(quat.angle(neck.rotations[:, JOINT["head"]]), 0.0, atol=1e-6)


def _collar_dirs(motion):
    """The collar bones' unit directions in the chest frame [T,2,3] (l, r)."""
    out = []
    for side in "lr":
        rest = OFFSETS[JOINT[f"{side}_shoulder"]] / np.linalg.norm(OFFSETS[JOINT[f"{side}_shoulder"]])
        local = motion.rotations[:, JOINT[f"{side}_collar"]]
        out.append(quat.rotate(local, np.broadcast_to(rest, local.shape[:-1] + (3,))))
    return np.stack(out, axis=1)


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_retargeted_collars_turn_about_their_sources_neutral_keeping_their_motion(mocap, source):
    """Where a skeleton puts its collar joint is a convention (motion.collars): the collars turn about
    their folder's measured mean direction, a swing in the chest frame, so a shrug still turns them as
    much and every limb still points as its source's does."""
    clip = bvh.load(mocap / SKELETON_CLIPS[source])
    as_is, _ = retarget(clip, collars=False)
    turned, src = retarget(clip)
    before, after = _collar_dirs(as_is), _collar_dirs(turned)

    def steps(d):
        return np.degrees(np.arccos(np.clip(np.sum(d[1:] * d[:-1], -1), -1, 1)))
    assert np.allclose(steps(after), steps(before), atol=1e-3)
    assert not np.allclose(after, before, atol=0.02)
    arms = [JOINT[f"{s}_{k}"] - 1 for s in "lr" for k in ("elbow", "wrist")]
    assert direction_errors_deg(turned, src)[:, arms].mean() < 2.0


def test_retargeted_shoulders_of_cmu_and_daz_sit_alike_against_the_chest(mocap):
    """CMU's collar bones rise 22 deg, Daz's fall 13 deg and never move: copied as they are, a CMU
    shoulder sits 6 cm above a Daz one against the chest. About their neutrals Daz's point out level on
    every frame and CMU's sit near them."""
    def mean_height(path, collars):
        motion, _ = retarget(bvh.load(mocap / path), collars=collars)
        return _collar_dirs(motion)[..., 1].mean()          # the collar bones' mean rise (sine)
    cmu, daz = SKELETON_CLIPS["cmu"], SKELETON_CLIPS["daz"]
    gap_before = mean_height(cmu, False) - mean_height(daz, False)
    gap_after = mean_height(cmu, True) - mean_height(daz, True)
    assert gap_before > 0.4 and abs(gap_after) < 0.5 * gap_before
    daz_after = _collar_dirs(retarget(bvh.load(mocap / daz))[0])
    assert np.allclose(daz_after, [[1.0, 0, 0], [-1.0, 0, 0]], atol=1e-3)
