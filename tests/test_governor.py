"""Adaptive N and K: the deadline watchdog against a simulated board whose CPU share drops and returns."""
import pytest

from edge.governor import GovernorSettings, SampleGovernor, rungs

PERIOD_MS = 1000 / 60


def frame_ms(n, share):
    """A frame's response time on a board that gives us `share` of a core: fixed + per-sample cost."""
    return (0.6 + 0.02 * n) / share


def run(governor, shares, plant=frame_ms):
    ns = []
    for share in shares:
        ns.append(governor.samples)
        governor.observe(plant(governor.samples, share))
    return ns


def test_an_idle_board_keeps_the_largest_n():
    g = SampleGovernor(PERIOD_MS, 32)
    assert set(run(g, [0.25] * 2000)) == {32} and list(g.changes) == []


def test_contention_halves_n_at_once_and_slack_brings_it_back_one_step_at_a_time():
    g = SampleGovernor(PERIOD_MS, 32)
    ns = run(g, [0.25] * 300 + [0.08] * 1200 + [0.25] * 3000)
    late = [frame_ms(n, s) > PERIOD_MS for n, s in zip(ns, [0.25] * 300 + [0.08] * 1200 + [0.25] * 3000, strict=True)]
    during = ns[300:1500]
    assert min(during) < 32 and during[-1] < 32
    assert sum(late) / len(late) < 0.005              # the bound: under 0.5 % of frames
    assert ns[-1] == 32                               # back up after the contention ends,
    assert ns.index(32, 1500) - 1500 <= 12 * g.base_hold   # within a step per second or so
    raises = [c for c in g.changes if c[3] == "slack"]
    assert all(g.ladder.index((b, kb)) == g.ladder.index((a, ka)) + 1 for _, a, b, _, ka, kb in raises)  # a rung each


def test_a_raise_that_is_undone_doubles_the_wait_before_the_next_try():
    g = SampleGovernor(PERIOD_MS, 32, settings=GovernorSettings(hold=120))
    # A busy board (one frame in 25 is slow) where the response time jumps past a point, as under a
    # CFS quota when a frame overruns its share of a period: 16 samples fit and 24 do not.
    frame = iter(range(10**9))
    def throttled(n, share):
        return 14.0 if n > 16 else (8.0 if next(frame) % 25 == 0 else 5.0)
    run(g, [0.25] * 6000, throttled)
    probes = [c[0] for c in g.changes if c[3] == "slack"]
    gaps = [b - a for a, b in zip(probes, probes[1:], strict=False)]
    assert len(probes) >= 3 and gaps == sorted(gaps) and gaps[-1] >= 4 * 120


def test_thresholds_must_be_ordered():
    with pytest.raises(ValueError):
        SampleGovernor(PERIOD_MS, 32, settings=GovernorSettings(high=0.4, low=0.5))


def test_the_change_history_is_bounded_and_the_count_is_not():
    from edge.governor import CHANGE_HISTORY
    g = SampleGovernor(16.7, 32)
    for k in range(3 * CHANGE_HISTORY):
        g.changes.append((k, 32, 16, "late"))
        g.change_count += 1
    assert len(g.changes) == CHANGE_HISTORY and g.change_count == 3 * CHANGE_HISTORY


def test_refinement_steps_share_the_ladder_one_step_first_then_all_from_n_32():
    assert rungs(128, 2) == [(1, 0), (1, 1), (2, 1), (4, 1), (8, 1), (16, 1), (24, 1), (32, 1), (32, 2), (48, 2),
                             (64, 2), (96, 2), (128, 2)]
    assert rungs(16, 2)[-2:] == [(16, 1), (16, 2)] and rungs(1, 3) == [(1, 0), (1, 1), (1, 2), (1, 3)]
    assert rungs(32, 0) == [(n, 0) for n in (1, 2, 4, 8, 16, 24, 32)]


class PipelineStub:
    """What the governor steers: N and K, applied when asked."""

    def __init__(self, samples, steps):
        self.samples, self.steps = samples, steps

    def set_samples(self, n):
        self.samples = n

    def set_refine_steps(self, k):
        self.steps = k


def test_with_a_target_live_contention_gives_up_samples_then_steps_and_takes_them_back():
    """Frames that refine a live target every frame, each step costing as much as 25 samples: a
    starved board drops to (1, 0) (the target then pulls only through the leg IK); with the usual
    share it climbs back a rung at a time to two steps at N=32 (where a frame takes more than `low`
    of the period, so it stays); deadlines hold throughout."""
    def plant(n, k, share):
        return (0.6 + 0.02 * n + 0.5 * k) / share
    g, pipe = SampleGovernor(PERIOD_MS, 128, max_steps=2), PipelineStub(128, 2)
    shares = [0.25] * 1200 + [0.05] * 1200 + [0.25] * 3600
    seen, late = [], 0
    for share in shares:
        ms = plant(pipe.samples, pipe.steps, share)
        late += ms > PERIOD_MS
        g.steer(pipe, ms)
        seen.append((pipe.samples, pipe.steps))
    assert all(n >= 32 and k == 2 for n, k in seen[1100:1200])       # the usual share: both steps, N >= 32
    assert seen[2300:2400] == [(1, 0)] * 100                         # starved: one sample, no step
    assert seen[-600:] == [(32, 2)] * 600                            # and back
    assert late / len(shares) < 0.005
