"""The SSI runtime: look-ahead latency, fixed memory, transitions and the no-SSI baseline."""
import os
import tracemalloc

import numpy as np
import pytest

from edge.pipeline import Pipeline
from edge.takes import from_sample
from tests.conftest import SAMPLE


@pytest.fixture(scope="module")
def take():
    return from_sample(SAMPLE)


@pytest.mark.parametrize("tau", [0, 3, 10])
def test_output_latency_is_exactly_tau_frames(take, tau):
    pipe = Pipeline(samples=4, lookahead=tau)
    for t in range(40):
        pose = pipe.step(take.signals.slice(t, t + 1))
        if t < tau:
            assert pose is None
        else:
            assert pose.frame == t - tau
    rest = pipe.flush()
    assert [p.frame for p in rest] == list(range(40 - tau, 40))


def test_single_sample_is_the_prior_mean_and_never_switches(take):
    pipe = Pipeline(samples=1)
    assert np.all(pipe.latents == 0) and pipe.lookahead == 0 and not pipe.ssi
    for t in range(100):
        assert pipe.step(take.signals.slice(t, t + 1)).sample == 0
    assert pipe.switches == []


def test_no_ssi_keeps_the_starting_sample_with_random_latents(take):
    pipe = Pipeline(samples=8, ssi=False)
    assert np.std(pipe.latents) > 0.5
    poses = [pipe.step(take.signals.slice(t, t + 1)) for t in range(200)]
    assert {p.sample for p in poses if p is not None} == {0} and pipe.switches == []


class ForcedSwitch:
    """A criterion that makes the current sample an outlier at one frame."""
    name, weight = "forced", 1.0

    def __init__(self, pipe, at):
        self.pipe, self.at = pipe, at

    def cost(self, ctx):
        c = np.zeros(len(ctx.positions))
        if ctx.frame == self.at:
            c[self.pipe.current] = 1.0
            c[3] = -0.1
        return c


def run_forced_switch(take, lookahead, at, frames, transition=10):
    """Run with a switch forced at frame `at`; returns the pipeline, {frame: (positions, sample, in
    transition)} and sample 3's own pose at frame at-1 as the buffer held it at the switch."""
    pipe = Pipeline(samples=6, lookahead=lookahead, transition=transition, criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=at))
    out, own_new = {}, None
    for t in range(frames):
        pose = pipe.step(take.signals.slice(t, t + 1))
        if pose is not None:
            out[pose.frame] = (pose.positions.copy(), pose.sample, pose.transition)
        if t == at:
            own_new = pipe.buffer.positions[pipe.buffer.slot(at - 1), 3].copy()
    return pipe, out, own_new


def test_transition_starts_at_the_oldest_unsent_frame_and_lands_on_the_new_sample(take):
    pipe, out, own_new = run_forced_switch(take, lookahead=10, at=40, frames=80)
    assert pipe.switches == [(40, 30, 0, 3)]
    assert [f for f in out if out[f][2]] == list(range(30, 40))          # frames t-tau .. t-tau+T-1
    assert all(out[f][1] == 0 for f in range(10, 30))
    assert all(out[f][1] == 3 for f in range(40, 70))
    # At the last transition frame the latent and GRU state are fully the new sample's.
    assert np.allclose(out[39][0], own_new, atol=1e-5)


def test_transition_longer_than_the_lookahead_continues_live(take):
    _, out, _ = run_forced_switch(take, lookahead=3, at=30, frames=60)
    assert [f for f in out if out[f][2]] == list(range(27, 37))


def test_ring_buffer_memory_is_fixed_over_20000_frames(take):
    pipe = Pipeline(samples=8, lookahead=10)
    n = take.frames
    frames = [take.signals.slice(t, t + 1) for t in range(n)]

    def rss_kb():
        with open(f"/proc/{os.getpid()}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))

    for t in range(2000):  # warm up caches and allocator pools
        pipe.step(frames[t % n])
    tracemalloc.start()
    before_py, _ = tracemalloc.get_traced_memory()
    before_rss = rss_kb()
    for t in range(20000):
        pipe.step(frames[t % n])
    after_py, _ = tracemalloc.get_traced_memory()
    after_rss = rss_kb()
    tracemalloc.stop()
    assert after_py - before_py < 100_000
    assert after_rss - before_rss < 2048
    assert pipe.buffer.nbytes() < 16 * 1024 * 1024
