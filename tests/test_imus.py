"""Extra body IMUs (edge.imus): names, the hold-and-fade of a lost tracker, DragPoser's drop protocol,
IMU noise, and what the synchroniser and the service make of them."""
import numpy as np
import pytest

from edge import quat
from edge.features import imu_features
from edge.imus import (FADE_S, IMU_LOCATIONS, LOST_AFTER_S, ImuNoise, dragposer_drops, fade, mask, parse_set)
from firmware_bridge.samples import TrackerSample
from firmware_bridge.sync import FrameSynchronizer
from test_sync import feed, run


def test_tracker_sets_parse_and_an_unknown_name_lists_the_valid_ones():
    assert parse_set("none") == () and parse_set("") == ()
    assert parse_set("all") == IMU_LOCATIONS
    assert parse_set("r_shin,l_shin") == ("l_shin", "r_shin")        # model order, whatever the user's
    with pytest.raises(ValueError, match="l_knee.*valid are chest, l_thigh"):
        parse_set("l_shin,l_knee")


def test_a_silent_tracker_is_held_then_fades_out_and_fades_back_in_when_it_returns():
    fps, T = 60.0, 200
    alive = np.ones((T, 1), bool)
    alive[50:120] = False                              # silent for 70 frames
    held = np.tile(quat.from_yaw(np.linspace(0, 1, T))[:, None], (1, 1, 1))
    flags, rot = fade(alive, fps, held)
    lost_n, fade_n = round(LOST_AFTER_S * fps), round(FADE_S * fps)
    assert np.all(flags[:50 + lost_n - 1] == 1.0)                        # not lost yet: full weight
    assert np.allclose(rot[50:120], held[49])                           # the last orientation is held
    down = np.diff(flags[50 + lost_n - 2:50 + lost_n + fade_n + 1, 0])
    assert np.all(down <= 0) and np.allclose(down[down < -1e-9], -1 / fade_n)  # a linear fade, no step
    assert np.all(flags[50 + lost_n + fade_n:120] == 0.0)
    assert np.allclose(rot[120:], held[120:])                            # back: live at once ...
    assert flags[120, 0] == pytest.approx(1 / fade_n) and flags[120 + fade_n, 0] == 1.0   # ... and its flag climbs


def test_dragposer_protocol_drops_one_worn_tracker_for_100_frames_at_1_percent_per_frame():
    rng = np.random.default_rng(0)
    worn = mask(("l_shin", "r_shin"))
    alive = dragposer_drops(rng, 60_000, worn)
    assert not alive[:, [0, 1, 2, 5, 6]].any()                           # only worn trackers are heard
    starts = np.flatnonzero(np.diff(alive[:, 3].astype(int)) == -1)
    assert 0.002 < len(starts) / 60_000 < 0.006                           # ~0.5 % per tracker (1 % over two)
    gaps = np.diff(np.flatnonzero(np.diff(alive[:, 3].astype(int))))[::2]
    assert np.median(gaps) == 100


def test_imu_noise_is_a_few_degrees_with_a_drifting_heading():
    rng = np.random.default_rng(1)
    T = 600
    true = np.tile(np.array([1.0, 0, 0, 0]), (T, 64, 7, 1))
    noisy = ImuNoise().apply(true, 60.0, rng)
    err = np.degrees(quat.angle(quat.mul(quat.inv(true), noisy)))
    assert 1.0 < np.median(err[0]) < 8.0 and err.max() < 25.0
    assert np.abs(np.degrees(quat.yaw(noisy[-1])) - np.degrees(quat.yaw(noisy[0]))).mean() > 1.0   # 10 s of drift


def test_absent_imus_read_zero_and_worn_ones_their_orientation_in_the_character_frame():
    yaw = quat.from_yaw(np.array(0.7))
    rot = np.tile(yaw, (7, 1))                         # every segment faces where the character faces
    f = imu_features(rot, mask(("l_shin",)), yaw)
    six, flags = f[:42].reshape(7, 6), f[42:]
    assert np.allclose(six[3], [1, 0, 0, 0, 1, 0]) and np.all(six[[0, 1, 2, 4, 5, 6]] == 0)
    assert np.array_equal(flags, mask(("l_shin",)))


def test_synchroniser_passes_each_extra_imu_and_fades_its_flag_when_it_goes_silent():
    sync = FrameSynchronizer(trackers=("waist", "l_shin", "r_foot"))
    events = feed(sync, 3.0)
    shin = quat.from_axis_angle(np.array([1.0, 0, 0]), np.array(0.4))
    for t in np.arange(0, 3.0, 0.01):
        if not 1.0 <= t < 2.0:                       # the shin tracker is silent for a second
            events.append((t + 0.001, "w", TrackerSample("l_shin", t - 3.0, shin)))
    events.sort(key=lambda e: e[0])
    frames = run(sync, events, 3.0)
    flag = np.array([sig.imu_flag[0, 3] for _, sig, _ in frames])
    tick = np.array([t for t, _, _ in frames])
    assert np.all(flag[(tick > 0.5) & (tick < 1.2)] == 1.0)                 # faded in at the start, then full
    assert np.all(flag[(tick > 1.6) & (tick < 2.0)] == 0.0)              # lost, faded out
    assert np.abs(np.diff(flag)).max() <= 1 / (FADE_S * 60) + 1e-9        # never a step
    assert np.all(flag[tick > 2.6] == 1.0)                                # back
    live = [sig for t, sig, _ in frames if 0.5 < t < 1.0][0]
    assert np.allclose(np.abs(live.imu_rot[0, 3] @ shin), 1.0)            # its orientation reached the frame
    assert np.all([sig.imu_flag[0, 6] == 0 for _, sig, _ in frames])      # configured but never heard: absent
    ages = frames[-1][2].ages
    assert ages["l_shin"] < 0.05 and ages["r_foot"] == np.inf
