"""Frame synchronisation: rates, clocks, late samples, loss and recovery."""
import numpy as np

from edge import quat
from firmware_bridge.samples import HeadsetSample, TrackerSample
from firmware_bridge.sync import ClockOffset, FrameSynchronizer


def head_at(t):
    return np.array([np.sin(t), 1.6, 0.5 * t]), quat.from_yaw(np.array(0.5 * t))


def waist_at(t):
    return quat.from_axis_angle(np.array([1.0, 0.0, 0.0]), np.array(0.8 * np.sin(2 * t)))


def headset(t_dev, t_true, hands_valid=(True, True)):
    p, q = head_at(t_true)
    hp = np.stack([p + [0.3, -0.5, 0.2], p + [-0.3, -0.5, 0.2]])
    return HeadsetSample(t_dev, p, q, hp, np.stack([q, q]), np.array(hands_valid))


def feed(sync, duration, head_hz=72, imu_hz=100, head_offset=5.0, imu_offset=-3.0, jitter=0.003, seed=0,
         shuffle=False, waist_gap=None, hand_gap=None):
    rng = np.random.default_rng(seed)
    events = []
    for t in np.arange(0, duration, 1 / head_hz):
        valid = not (hand_gap and hand_gap[0] <= t < hand_gap[1])
        events.append((t + 0.002 + rng.uniform(0, jitter), "h", headset(t + head_offset, t, (valid, True))))
    for t in np.arange(0, duration, 1 / imu_hz):
        if waist_gap and waist_gap[0] <= t < waist_gap[1]:
            continue
        events.append((t + 0.001 + rng.uniform(0, jitter), "w", TrackerSample("waist", t + imu_offset, waist_at(t))))
    events.sort(key=lambda e: e[0])
    if shuffle:  # deliver in a scrambled order within small bursts
        for i in range(0, len(events) - 4, 4):
            rng.shuffle(events[i:i + 4])
    return events


def run(sync, events, until, hz=60):
    frames, k = [], 0
    for tick in np.arange(0.2, until, 1 / hz):
        while k < len(events) and events[k][0] <= tick:
            recv, kind, s = events[k]
            (sync.add_headset if kind == "h" else sync.add_tracker)(s, received=recv)
            k += 1
        frames.append((tick, *sync.frame(tick)))
    return frames


def test_clock_offset_is_the_minimum_delay():
    c = ClockOffset()
    for i, d in enumerate([0.010, 0.003, 0.020, 0.004]):
        c.update(i * 0.01 + 100.0, i * 0.01 + d)
    assert np.isclose(c.offset, -100.0 + 0.003)


def test_streams_at_their_own_rates_and_clocks_interpolate_to_the_model_tick():
    sync = FrameSynchronizer(latency=0.02)
    frames = run(sync, feed(sync, 4.0), 4.0)
    errs_p, errs_q = [], []
    for tick, sig, health in frames[30:]:
        t = tick - 0.02 - 0.002         # board time minus the latency we asked for and the minimum delay
        p, q = head_at(t)
        errs_p.append(np.linalg.norm(sig.head_pos[0] - p))
        errs_q.append(np.degrees(quat.angle(quat.mul(quat.inv(waist_at(t + 0.001)), sig.waist_rot[0]))))
        assert not any(health.lost.values())
    assert np.max(errs_p) < 0.01 and np.max(errs_q) < 1.0


def test_out_of_order_samples_land_in_place():
    a = run(FrameSynchronizer(latency=0.03), feed(None, 3.0), 3.0)
    b = run(FrameSynchronizer(latency=0.03), feed(None, 3.0, shuffle=True), 3.0)
    pa = np.array([f[1].head_pos[0] for f in a[20:]])
    pb = np.array([f[1].head_pos[0] for f in b[20:]])
    assert np.abs(pa - pb).max() < 0.01


def test_silent_waist_is_lost_turns_with_the_headset_and_blends_back_without_a_snap():
    sync = FrameSynchronizer(lost_after=0.25, blend_s=0.5)
    frames = run(sync, feed(sync, 5.0, waist_gap=(2.0, 3.0)), 5.0)
    lost = np.array([f[2].lost["waist"] for f in frames])
    ticks = np.array([f[0] for f in frames])
    assert not lost[ticks < 2.2].any() and lost[(ticks > 2.3) & (ticks < 2.95)].all() and not lost[ticks > 3.1].any()
    w = np.array([f[1].waist_rot[0] for f in frames])
    heads = np.array([f[1].head_rot[0] for f in frames])
    gone = (ticks > 2.3) & (ticks < 2.95)
    held = w[gone]
    # Held while lost, but turning with the headset: the waist-to-head heading offset stays fixed.
    offset = np.unwrap(quat.yaw(held) - quat.yaw(heads[gone]))
    assert np.ptp(offset) < 1e-6 and np.ptp(quat.yaw(held)) > 0.1
    step = np.degrees(quat.angle(quat.mul(quat.inv(w[:-1]), w[1:])))
    after = (ticks[1:] > 3.0) & (ticks[1:] < 3.6)
    assert step[after].max() < 6.0                          # blended back, no snap to the live value
    live_jump = np.degrees(quat.angle(quat.mul(quat.inv(held[-1]), waist_at(3.0))))
    assert live_jump > 20.0                                  # ...which would have been a big one


def test_lost_controller_drifts_to_beside_the_body_and_returns_smoothly():
    sync = FrameSynchronizer(decay_s=1.0, blend_s=0.5)
    frames = run(sync, feed(sync, 6.0, hand_gap=(2.0, 4.0)), 6.0)
    ticks = np.array([f[0] for f in frames])
    left = np.array([f[1].hand_pos[0, 0] for f in frames])
    heads = np.array([f[1].head_pos[0] for f in frames])
    i = np.searchsorted(ticks, 3.9)
    assert frames[i][2].lost["l_hand"] and not frames[i][2].lost["r_hand"]
    assert abs((left[i] - heads[i])[1] + 0.75) < 0.05       # hanging at hip height under the head
    speed = np.linalg.norm(np.diff(left, axis=0), axis=-1) * 60
    assert speed[(ticks[1:] > 4.0) & (ticks[1:] < 4.8)].max() < 5.0


def test_non_finite_samples_are_ignored():
    sync = FrameSynchronizer()
    bad = headset(0.0, 0.0)
    bad.head_pos = np.array([np.nan, 0, 0])
    sync.add_headset(bad, received=0.0)
    sig, health = sync.frame(0.1)
    assert sig is None and health.lost["head"]


def test_the_clock_offset_is_the_windows_minimum_as_values_come_and_go():
    """ClockOffset keeps its window's minimum as samples arrive and leave (a minimum that leaves is
    looked for again); it is always window.min(), through repeats of the minimum and a NaN."""
    rng = np.random.default_rng(0)
    for size in (3, 7, 50):
        c = ClockOffset(window=size)
        for i in range(2000):
            device, received = rng.uniform(0, 100), rng.uniform(0, 100)
            if i % 97 == 0:
                received = device + 5.0                     # the same offset again
            if i == 500:
                received = np.nan                           # held for one window, then gone
            got = c.update(device, received)
            want = float(c.window.min())
            assert got == want or (np.isnan(got) and np.isnan(want)), (size, i)
        assert np.isfinite(c.offset)
