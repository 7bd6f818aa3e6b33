"""The upper body's one-euro filter (edge.smooth): it calms a shaking torso, follows a fast move, leaves
the head and the wrists alone, hands a move between samples over without a step, and the compiled
core runs the same filter."""
import numpy as np
import pytest

from edge import native
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.skeleton import JOINT_NAMES
from edge.smooth import PASS_THROUGH, SMOOTH_COLS, UpperBodySmoother
from tests.conftest import SAMPLE
from tests.test_pipeline import from_sample

FPS = 60.0
D = 120                                  # the decoder's 6D width (20 predicted joints)


def run(smoother, values):
    """Filter a [T, rows, D] sequence frame by frame; returns the filtered copy."""
    out = values.astype(np.float32).copy()
    for t in range(len(out)):
        smoother.apply(out[t], out.shape[1])
    return out


def test_a_still_pose_passes_through_unchanged():
    pose = np.random.default_rng(0).normal(size=(1, 1, D)).astype(np.float32)
    out = run(UpperBodySmoother(1, 1, FPS), np.repeat(pose, 30, 0))
    assert np.array_equal(out, np.repeat(pose, 30, 0))


def test_shaking_is_damped_and_a_fast_move_is_followed_closely():
    rng = np.random.default_rng(1)
    T = 240
    still = np.zeros((T, 1, D)) + rng.normal(0, 0.01, (T, 1, D))            # 1 % noise on a still pose
    out = run(UpperBodySmoother(1, 1, FPS), still)
    jerk = lambda x: np.abs(np.diff(x[:, 0, :SMOOTH_COLS], 3, axis=0)).mean()
    assert jerk(out) < jerk(still) / 2
    # A fast turn (2 units/s of 6D, about a 115 deg/s rotation) is followed within a few frames' lag.
    ramp = (np.arange(T) / FPS * 2.0)[:, None, None] * np.ones((T, 1, D))
    out = run(UpperBodySmoother(1, 1, FPS), ramp)
    lag = (ramp[-1, 0, 0] - out[-1, 0, 0]) / (2.0 / FPS)
    assert 0 < lag < 3.0, f"{lag:.2f} frames behind"


def test_the_head_the_left_wrist_and_the_joints_after_the_elbows_pass_through():
    noisy = np.random.default_rng(2).normal(size=(50, 2, D))
    out = run(UpperBodySmoother(2, 1, FPS), noisy)
    for j in PASS_THROUGH:
        np.testing.assert_array_equal(out[..., j * 6:(j + 1) * 6], noisy[..., j * 6:(j + 1) * 6].astype(np.float32))
    np.testing.assert_array_equal(out[..., SMOOTH_COLS:], noisy[..., SMOOTH_COLS:].astype(np.float32))
    assert not np.allclose(out[..., :18], noisy[..., :18], atol=1e-3)          # the spine, chest and neck are filtered


def test_each_row_is_filtered_with_its_own_state():
    seq = np.random.default_rng(3).normal(size=(40, 3, D))
    together = run(UpperBodySmoother(3, 1, FPS), seq)
    for r in range(3):
        alone = run(UpperBodySmoother(1, 1, FPS), seq[:, r:r + 1])
        np.testing.assert_array_equal(together[:, r:r + 1], alone)


def test_a_move_starts_on_the_shown_samples_filter_and_lands_on_the_new_ones():
    sm = UpperBodySmoother(3, 2, FPS)
    seq = np.random.default_rng(4).normal(size=(20, 3, D)).astype(np.float32)
    for t in range(20):
        sm.apply(seq[t], 2)
    for a, like in ((0.0, 0), (1.0, 1)):
        sm.blend_into(0, 1, a, 2)
        np.testing.assert_array_equal(sm.prev[2], sm.prev[like])
        np.testing.assert_array_equal(sm.speed[2], sm.speed[like])
    sm.blend_into(0, 1, 0.25, 2)
    np.testing.assert_allclose(sm.prev[2], 0.75 * sm.prev[0] + 0.25 * sm.prev[1])
    # As a slot kept them: the state before that slot's frame.
    sm.remember(1, 2)
    before = sm.prev[:2].copy()
    sm.apply(seq[0], 2)
    sm.blend_into(0, 1, 1.0, 2, slot=1)
    np.testing.assert_array_equal(sm.prev[2], before[1])


@pytest.mark.skipif(not native.load(), reason="needs the compiled core")
def test_the_compiled_filter_is_the_numpy_one_to_the_bit():
    pipe = Pipeline(PipelineOptions(samples=4))
    sm, path = pipe.smoother, pipe.path
    rng = np.random.default_rng(5)
    sm.prime(rng.normal(size=(pipe.rows, D)).astype(np.float32), pipe.rows)
    state = sm.prev.copy(), sm.speed.copy()
    rows = rng.normal(size=(3, pipe.recompute.rot6d.shape[1])).astype(np.float32)
    results = []
    for compiled in (True, False):
        sm.prev[:], sm.speed[:] = state
        pipe.recompute.rot6d[:1] = rows[:1]
        (path if compiled else pipe.reference).smooth_recomputed(0, 4)
        results.append((pipe.recompute.rot6d[0].copy(), sm.prev[4].copy(), sm.speed[4].copy()))
    for a, b in zip(*results, strict=True):
        np.testing.assert_array_equal(a, b)


def jerk_of(positions, joints):
    idx = [JOINT_NAMES.index(j) for j in joints]
    return np.linalg.norm(np.diff(positions[:, idx], 3, axis=0), axis=-1).mean()


@pytest.mark.parametrize("use_native", [True, False])
def test_the_filter_calms_the_torso_and_arms_and_keeps_the_wrists_on_the_controllers(use_native):
    take = from_sample(SAMPLE)
    runs = {}
    for cut in (0.0, 3.0):
        pipe = Pipeline(PipelineOptions(samples=1, smooth_min_cutoff=cut, use_native=use_native))
        poses = []
        for t in range(take.frames):
            pose = pipe.step(take.signals.slice(t, t + 1))
            poses.append(pose.positions.copy())
        runs[cut] = np.array(poses)
    # On this walk (v0.5.1): chest 0.82x, neck 0.74x, collars 0.76x, shoulders 0.88x. The elbows, whose
    # jerk here is already the truth's (76.5 against 76.4), 1.00x; on val's unseen people the filter takes
    # them from 1.34x the truth's to 1.12x (the model card's "The arms a user sees").
    for joints in (("chest",), ("neck",), ("l_collar", "r_collar"), ("l_shoulder", "r_shoulder")):
        assert jerk_of(runs[3.0], joints) < 0.95 * jerk_of(runs[0.0], joints), joints
    assert jerk_of(runs[3.0], ("l_elbow", "r_elbow")) <= 1.001 * jerk_of(runs[0.0], ("l_elbow", "r_elbow"))
    wrists = [JOINT_NAMES.index(j) for j in ("l_wrist", "r_wrist")]
    np.testing.assert_allclose(runs[3.0][:, wrists], runs[0.0][:, wrists], atol=1e-6)
