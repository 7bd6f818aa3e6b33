"""Training's "one person into another" (motion.augment) and its windows drawn by person
(motion.dataset.WindowDraw): the mirror is exact on the canonical skeleton, a re-timed window is the
clip read by the resampler at another rate, and each person gets the share the rule gives."""
import numpy as np
import pytest

from edge import quat
from edge.skeleton import JOINT, NUM_JOINTS
from motion import augment
from motion import dataset as ds
from motion.retarget import Motion, resample
from motion.synth import world_pose

REFLECT = np.array([-1.0, 1.0, 1.0])


def random_motion(frames=40, seed=0):
    rng = np.random.default_rng(seed)
    rot = quat.unroll(quat.normalize(rng.standard_normal((frames, NUM_JOINTS, 4)) + [3, 0, 0, 0]))
    return rot, rng.standard_normal((frames, 3))


def test_mirroring_twice_is_the_identity():
    rot, root = random_motion()
    np.testing.assert_array_equal(augment.mirror_rotations(augment.mirror_rotations(rot)), rot)
    np.testing.assert_array_equal(augment.mirror_root(augment.mirror_root(root)), root)
    c = np.random.default_rng(1).random((10, 2))
    np.testing.assert_array_equal(augment.mirror_contacts(augment.mirror_contacts(c)), c)
    m = np.arange(7.0)
    np.testing.assert_array_equal(augment.mirror_imus(augment.mirror_imus(m)), m)


def test_a_mirrored_motions_fk_is_the_reflected_fk_with_sides_swapped():
    rot, root = random_motion()
    world_rot, pos = world_pose(rot, root)
    mirror_rot, mirror_pos = world_pose(augment.mirror_rotations(rot), augment.mirror_root(root))
    np.testing.assert_allclose(mirror_pos, (pos * REFLECT)[:, augment.MIRROR_JOINTS], atol=1e-12)
    S = np.diag(REFLECT)
    np.testing.assert_allclose(mirror_rot, (S @ world_rot @ S)[:, augment.MIRROR_JOINTS], atol=1e-12)
    # the left foot of the mirror image is where the reflected right foot was
    np.testing.assert_allclose(mirror_pos[:, JOINT["l_toe"]], pos[:, JOINT["r_toe"]] * REFLECT, atol=1e-12)


def test_the_imu_swap_takes_each_side_to_its_twin():
    from edge.imus import IMU_LOCATIONS
    names = np.array(IMU_LOCATIONS)
    swapped = augment.mirror_imus(names)
    for a, b in zip(names, swapped, strict=True):
        assert b == (a if a == "chest" else {"l": "r", "r": "l"}[a[0]] + a[1:])


@pytest.fixture(scope="module")
def val(mocap):
    return ds.build(mocap, "val")


def test_a_mirrored_window_is_the_reflected_window_in_every_target(val):
    """Rendered with the headset, controllers and IMUs synthesised from the mirror image: the head-anchored
    truth is the reflected one with sides swapped, the contacts swap, and so do the worn IMUs."""
    rng = np.random.default_rng(5)
    d = ds.draw_batch(rng, rng.choice(ds.window_starts(val, 60), 16), 60, with_imus=False)
    plain = ds.render_batch(val, d, 60)
    mirrored = ds.render_batch(val, dict(d, mirror=np.ones(16, bool)), 60)
    want = (plain["gt_rel"].astype(np.float64) * REFLECT)[:, :, augment.MIRROR_JOINTS]
    np.testing.assert_allclose(mirrored["gt_rel"], want, atol=2e-5)
    np.testing.assert_array_equal(mirrored["contacts"], plain["contacts"][..., ::-1])
    assert not np.allclose(mirrored["gt_rel"], plain["gt_rel"], atol=1e-2)


def test_a_mirrored_window_wears_its_imus_on_the_other_side(val):
    """The IMU drawn for the person's left foot sits on the mirror image's right foot: its presence flag
    (the features' last seven columns) moves to r_foot, and what it reads is the mirrored foot's."""
    from edge.features import NUM_FEATURES
    from edge.imus import IMU_INDEX
    rng = np.random.default_rng(6)
    d = ds.draw_batch(rng, rng.choice(ds.window_starts(val, 60), 8), 60)
    d["worn"][:] = 0
    d["worn"][:, IMU_INDEX["l_foot"]] = 1
    d["alive"][:] = d["worn"][None] > 0
    flags = ds.render_batch(val, dict(d, mirror=np.ones(8, bool)), 60)["features"][..., NUM_FEATURES - 7:NUM_FEATURES]
    assert (flags[..., IMU_INDEX["r_foot"]] == 1).all() and (flags[..., IMU_INDEX["l_foot"]] == 0).all()


def test_a_window_at_tempo_one_is_the_window_as_recorded(val):
    rng = np.random.default_rng(7)
    d = ds.draw_batch(rng, rng.choice(ds.window_starts(val, 60), 8), 60, with_imus=False)
    plain = ds.window_motion(val, d, 60)
    at_one = ds.window_motion(val, dict(d, speed=np.ones(8)), 60)
    for a, b in zip(plain, at_one, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_a_window_at_another_tempo_is_the_clip_resampled_to_that_rate():
    """A window read at speed s is what motion.retarget.resample makes of the clip at 60/s Hz."""
    rot, root = random_motion(200, seed=3)
    cs = ds.ClipSet(["x"], np.array([0]), rot.astype(np.float32), root.astype(np.float32), np.zeros((200, 2)))
    rot32, root32 = cs.rotations.astype(np.float64), cs.root.astype(np.float64)
    for speed in (0.8, 1.25, 2.0):
        got_rot, got_root, _ = ds.window_motion(cs, {"starts": np.array([0]), "speed": np.array([speed])}, 60)
        ref = resample(Motion(rot32, root32, 60.0 * 1.0), 60.0 / speed)
        np.testing.assert_allclose(got_root[:, 0], ref.root[:60], atol=1e-9)
        same = np.abs((got_rot[:, 0] * ref.rotations[:60]).sum(-1))        # q and -q are one rotation
        np.testing.assert_allclose(same, 1.0, atol=1e-9)


def test_tempos_are_drawn_over_the_whole_range_alike_slower_and_faster():
    s = augment.draw_speeds(np.random.default_rng(0), 20000, 0.8, 1.25)
    assert 0.8 <= s.min() < 0.81 and 1.24 < s.max() <= 1.25
    assert np.mean(s < 1) == pytest.approx(0.5, abs=0.02)


def people_set():
    """Three subjects: "a" 10 minutes, "b" 1 minute, and a folder of three unlabelled actors, 30."""
    subjects = np.array(["a", "b", "c:unlabelled(3 actors)"])
    frames = np.array([36000, 3600, 108000])
    starts = np.concatenate([[0], np.cumsum(frames)[:-1]])
    n = frames.sum()
    return ds.ClipSet(["a", "b", "c"], starts, np.zeros((n, 1, 4), np.float32), np.zeros((n, 3), np.float32),
                      np.zeros((n, 2), np.float32), None, subjects)


@pytest.mark.parametrize("rule, want", [
    ("frames", [36000 / 147600, 3600 / 147600, 108000 / 147600]),
    ("people", [1 / 5, 1 / 5, 3 / 5]),
    ("sqrt", np.array([np.sqrt(10), 1, 3 * np.sqrt(10)]) / (4 * np.sqrt(10) + 1)),
    ("capped", np.array([5, 1, 3 * 5]) / 21),
])
def test_each_person_gets_the_share_of_windows_the_rule_gives(rule, want):
    cs = people_set()
    starts = ds.window_starts(cs, 60)
    draw = ds.WindowDraw(cs, starts, rule, cap_minutes=5)
    got = draw.draw(np.random.default_rng(0), 200_000)
    clip = np.searchsorted(cs.starts, got, side="right") - 1
    share = np.bincount(clip, minlength=3) / len(got)
    np.testing.assert_allclose(share, want, atol=0.005)
    assert len(draw.table()) >= 1


def test_the_frames_rule_draws_what_training_always_drew():
    cs = people_set()
    starts = ds.window_starts(cs, 60)
    got = ds.WindowDraw(cs, starts, "frames").draw(np.random.default_rng(4), 100)
    np.testing.assert_array_equal(got, np.random.default_rng(4).choice(starts, 100))


def test_drawing_by_person_without_subjects_says_how_to_get_them():
    cs = people_set()
    cs.subjects = None
    with pytest.raises(ValueError, match="rebuild the pack"):
        ds.WindowDraw(cs, ds.window_starts(cs, 60), "people")
