"""The SSI runtime: look-ahead latency, fixed memory, transitions and the no-SSI baseline."""
import os
import tracemalloc

import numpy as np
import pytest

from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from motion.takes import from_sample
from tests.conftest import SAMPLE


@pytest.fixture(scope="module")
def take():
    return from_sample(SAMPLE)


@pytest.mark.parametrize("tau", [0, 3, 10])
def test_output_latency_is_exactly_tau_frames(take, tau):
    pipe = Pipeline(PipelineOptions(samples=4, lookahead=tau))
    for t in range(40):
        pose = pipe.step(take.signals.slice(t, t + 1))
        if t < tau:
            assert pose is None
        else:
            assert pose.frame == t - tau
    rest = pipe.flush()
    assert [p.frame for p in rest] == list(range(40 - tau, 40))


def test_by_default_the_board_sends_frame_t_at_tick_t(take):
    """Present-frame output is the default, for the pipeline and for the board's config: each tick sends
    the pose of the frame it was given, at every N (look-ahead is an offline option)."""
    from firmware_bridge import config as config_mod
    cfg = config_mod.from_dict({"headset": {"url": "serial:///dev/null?role=headset"},
                                "runtime": {"samples": 8}}, "default")
    assert cfg.lookahead == 0
    pipe = Pipeline(cfg.pipeline_options())
    for t in range(40):
        assert pipe.step(take.signals.slice(t, t + 1)).frame == t
    assert Pipeline(PipelineOptions(samples=8)).lookahead == 0 and pipe.flush() == []


def test_a_switch_at_tau_0_is_eased_forward_from_the_shown_pose(take):
    """With no look-ahead a move starts at the frame it is detected and eases from the pose already shown:
    the first frame of a move is its source sample's own (weight ~0), not a jump."""
    pipe, out, own_new = run_forced_switch(take, lookahead=0, at=40, frames=80)
    t, s0, c, n = pipe.switches[0]
    assert s0 == t == 40
    assert out[s0][2] and not out[s0 + pipe.transition][2]          # frames s0..s0+T-1 are the move
    jump = lambda f: np.linalg.norm(out[f][0] - out[f - 1][0], axis=-1).max()     # noqa: E731
    before = max(jump(f) for f in range(s0 - 10, s0))
    assert jump(s0) <= 1.5 * before, f"the move's first frame jumped {jump(s0):.3f} m (motion before: {before:.3f})"


def test_the_sample_moved_to_takes_the_shown_samples_foot_locks(take):
    """A switch hands the shown sample's foot locks to the sample it moves to, so a planted foot stays
    where the user sees it instead of sliding to where the other sample had planted it."""
    pipe = Pipeline(PipelineOptions(samples=6, lookahead=0, precision="fp32"), criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=40))      # from sample 0 to sample 3 at frame 40
    for t in range(41):
        pipe.step(take.signals.slice(t, t + 1))
        if t == 39:
            differed = not np.array_equal(pipe.feet.lock_pos[3], pipe.feet.lock_pos[0])
    f = pipe.feet
    assert differed and list(pipe.switches) == [(40, 40, 0, 3)]
    assert np.array_equal(f.lock_pos[3], f.lock_pos[0]) and np.array_equal(f.locked[3], f.locked[0])
    assert np.array_equal(f.weight[3], f.weight[0])


def test_the_shown_sample_goes_home_to_the_prior_mean_once_that_costs_no_more(take):
    """Homing (selection.home_after): after a move away from sample 0, the output moves back to it with
    the same eased move once sample 0 has cost no more than the shown sample for home_after frames in a
    row (counted from when a new move may start: the last one has been sent)."""
    pipe = Pipeline(PipelineOptions(samples=6, lookahead=0, precision="fp32"), criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=40))      # to sample 3 at 40; all costs 0 after
    pipe.home_after = 10
    for t in range(100):
        pipe.step(take.signals.slice(t, t + 1))
    assert list(pipe.switches) == [(40, 40, 0, 3), (59, 59, 3, 0)] and pipe.current == 0


def test_single_sample_is_the_prior_mean_and_never_switches(take):
    pipe = Pipeline(PipelineOptions(samples=1))
    assert np.all(pipe.latents == 0) and pipe.lookahead == 0 and not pipe.ssi
    for t in range(100):
        assert pipe.step(take.signals.slice(t, t + 1)).sample == 0
    assert list(pipe.switches) == []


def test_no_ssi_keeps_the_starting_sample_with_random_latents(take):
    pipe = Pipeline(PipelineOptions(samples=8, ssi=False))
    assert np.std(pipe.latents) > 0.5
    poses = [pipe.step(take.signals.slice(t, t + 1)) for t in range(200)]
    assert {p.sample for p in poses if p is not None} == {0} and list(pipe.switches) == []


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
    # fp32: a recomputed frame then matches the live one exactly (int8's per-batch activation scales do not)
    pipe = Pipeline(PipelineOptions(samples=6, lookahead=lookahead, transition=transition, precision="fp32"), criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=at))
    out, own_new = {}, None
    for t in range(frames):
        pose = pipe.step(take.signals.slice(t, t + 1))
        if pose is not None:
            out[pose.frame] = (pose.positions.copy(), pose.sample, pose.transition)
        if t == at and lookahead > 0:
            own_new = pipe.pose_from_buffer(at - 1, 3)[0]
    return pipe, out, own_new


def test_transition_starts_at_the_oldest_unsent_frame_and_lands_on_the_new_sample(take):
    pipe, out, own_new = run_forced_switch(take, lookahead=10, at=40, frames=80)
    assert list(pipe.switches) == [(40, 30, 0, 3)]
    assert [f for f in out if out[f][2]] == list(range(30, 40))          # frames t-tau .. t-tau+T-1
    assert all(out[f][1] == 0 for f in range(10, 30))
    assert all(out[f][1] == 3 for f in range(40, 70))
    # At the last transition frame the latent and GRU state are fully the new sample's.
    assert np.allclose(out[39][0], own_new, atol=1e-5)


def test_transition_longer_than_the_lookahead_continues_live(take):
    _, out, _ = run_forced_switch(take, lookahead=3, at=30, frames=60)
    assert [f for f in out if out[f][2]] == list(range(27, 37))


def test_ring_buffer_memory_is_fixed_over_20000_frames(take):
    pipe = Pipeline(PipelineOptions(samples=8, lookahead=10))
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


def frame_memory(pipe, frames, count):
    """Each of `count` frames' transient peak of traced memory (bytes above what was live before it),
    and whether an SSI switch started in it; tracemalloc must be running."""
    peaks, switched = np.zeros(count), np.zeros(count, bool)
    for k in range(count):
        before, was = tracemalloc.get_traced_memory()[0], pipe.switch_count
        tracemalloc.reset_peak()
        pipe.step(frames[k % len(frames)])
        peaks[k], switched[k] = tracemalloc.get_traced_memory()[1] - before, pipe.switch_count > was
    return peaks, switched


@pytest.mark.skipif(not __import__("edge.native").native.load(), reason="the compiled core is the board's frame")
def test_a_frame_makes_no_arrays_at_any_n_and_a_switch_none_either(take):
    """The board's frame allocates no arrays: what a frame's memory peaks at is the Python bindings'
    own call objects (ctypes arguments, ONNX Runtime's run wrapper, under 1 KB), the same at N=2 and
    N=128 (a temporary per sample would be 1 KB more at N=128), and a frame that starts an SSI switch
    (which re-runs the look-ahead) adds no more than another call's worth."""
    frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    runs = {}
    # The physical criterion at 6 (the shipped 1 switches once here): the test needs a few switches.
    selection = Pipeline(PipelineOptions()).manifest["selection"]
    selection = {**selection, "physical": {**selection["physical"], "weight": 6.0}}
    for n in (2, 128):
        pipe = Pipeline(PipelineOptions(samples=n, selection=selection))
        for t in range(200):
            pipe.step(frames[t % len(frames)])
        tracemalloc.start()
        try:
            runs[n] = frame_memory(pipe, frames[200:] + frames[:200], 600)
        finally:
            tracemalloc.stop()
    (small, _), (large, switched) = runs[2], runs[128]
    assert switched.sum() >= 3, "the take should make the SSI switch a few times at N=128"
    assert np.median(large) <= 1024 and abs(np.median(large) - np.median(small)) <= 64
    assert np.percentile(large[~switched], 99) <= 2048
    assert large[switched].max() <= 2048


@pytest.mark.skipif(not __import__("edge.native").native.load(), reason="the compiled core is the board's frame")
def test_a_refined_frame_makes_no_arrays_either(take):
    """A frame that refines a live target two steps (edge.refine: its batches, FK, the C step, the
    refined row's decode) makes no arrays: its memory peaks within 512 bytes of a frame without one
    (here +191 to +368, as the plain frame's own peak moves: a few small Python objects, the live terms'
    list and such); the refiner's latents,
    batches and scratch are all preallocated (a temporary as large as the batch's 30 x 30 steps, 3.7
    KB, fails this; one small enough to be freed before the frame's peak would not show)."""
    from edge.skeleton import JOINT
    frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    runs = {}
    for live in (False, True):
        pipe = Pipeline(PipelineOptions(samples=8, refine={"steps": 2}))
        for t in range(150):
            pipe.step(frames[t % len(frames)])
        if live:
            pipe.refiner.add_target("l_toe", pipe.out.positions[JOINT["l_toe"]] + [0.0, 0.4, 0.2], first=0,
                                    last=1 << 40)
        tracemalloc.start()
        try:
            runs[live] = frame_memory(pipe, frames[150:] + frames[:150], 300)[0]
        finally:
            tracemalloc.stop()
        assert (pipe.refiner.applied >= 290) == live
    assert np.median(runs[True]) - np.median(runs[False]) <= 512
    assert np.percentile(runs[True], 99) <= 2048


# ------------------------------------------------------------------ adaptive N

# int8 quantizes the decoder's activations per call, over the whole batch: a row's output depends on
# the other rows by a little, so with int8 a change of N moves the shown sample by millimetres; and
# where a foot's contact probability sits at 0.5, that can tip its lock one way or the other for a
# step (a few centimetres at the foot). fp32 must be exact; int8 close on all but a few frames.
@pytest.mark.parametrize("precision,tol,tail", [("fp32", 1e-5, 1e-5), ("int8", 0.015, 0.08)])
def test_changing_n_leaves_the_shown_sample_untouched(take, precision, tol, tail):
    """Without SSI the shown sample is sample 0: lowering and raising N around it must not move it."""
    fixed, adaptive = (Pipeline(PipelineOptions(samples=16, ssi=False, precision=precision)) for _ in range(2))
    plan = {50: 4, 120: 16, 180: 1}
    live, moved = [], []
    for t in range(240):
        if t in plan:
            adaptive.set_samples(plan[t])
        sig = take.signals.slice(t, t + 1)
        a, b = fixed.step(sig), adaptive.step(sig)
        live.append(adaptive.samples)
        if a is not None:
            assert a.frame == b.frame and a.sample == b.sample == 0
            moved.append(np.abs(a.positions - b.positions).max())
    assert np.percentile(moved, 95) <= tol and max(moved) <= tail
    assert (live[49], live[50], live[119], live[120], live[-1]) == (16, 4, 4, 16, 1)
    assert adaptive.decoder.rows == 2 and adaptive.autoencoder.rows == 1


def test_dropping_the_shown_sample_moves_to_a_kept_one_with_the_ssi_transition(take):
    pipe = Pipeline(PipelineOptions(samples=6, lookahead=10), criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=40))      # shows sample 3 from frame 40 on
    out = {}
    for t in range(120):
        if t == 70:
            pipe.set_samples(2)                                    # sample 3 is not among the first 2
        pose = pipe.step(take.signals.slice(t, t + 1))
        if pose is not None:
            out[pose.frame] = (pose.sample, pose.transition, pipe.samples)
    assert list(pipe.switches) == [(40, 30, 0, 3), (70, 60, 3, 0)]
    assert [f for f in out if out[f][1]] == list(range(30, 40)) + list(range(60, 70))
    # The smaller N applies once no transition frame still has to be computed from sample 3: here the
    # whole transition (60..69) was recomputed inside the look-ahead at frame 70, so from frame 71 on
    # (output frame 61); never while sample 3 is still read.
    assert {out[f][2] for f in out if f < 61} == {6} and {out[f][2] for f in out if f >= 61} == {2}
    assert sorted(out) == list(range(110))


def test_with_ssi_on_a_smaller_n_only_ever_shows_kept_samples(take):
    pipe = Pipeline(PipelineOptions(samples=12, lookahead=10))
    shown_after = []
    for t in range(400):
        if t == 100:
            pipe.set_samples(3)
        if t == 250:
            pipe.set_samples(12)
        pose = pipe.step(take.signals.slice(t, t + 1))
        if pose is not None and pipe.samples == 3 and t < 250:
            shown_after.append(pose.sample)
    assert shown_after and set(shown_after) <= {0, 1, 2}
    assert pipe.samples == 12


def test_a_live_transition_keeps_its_source_sample_running_until_its_last_frame(take):
    """tau=3 < T=10: the transition from sample 3 runs live to frame 76, so N drops after that step."""
    pipe = Pipeline(PipelineOptions(samples=6, lookahead=3), criteria=[])
    pipe.criteria.criteria.append(ForcedSwitch(pipe, at=40))
    live = {}
    for t in range(90):
        if t == 70:
            pipe.set_samples(2)
        pipe.step(take.signals.slice(t, t + 1))
        live[t] = pipe.samples
    assert pipe.switches[-1] == (70, 67, 3, 0) and pipe.trans_end == 76
    assert {live[t] for t in range(70, 76)} == {6} and {live[t] for t in range(76, 90)} == {2}


@pytest.mark.parametrize("tau", [0, 4])
def test_growing_n_during_a_move_keeps_the_moves_frames(take, tau):
    """N goes from 4 to 6 two frames into a move (the governor may raise N at any frame): the move's
    spare row, row 4 until then, becomes sample 4's, and the move's buffered frames come out as they
    would have without the change (before, they showed the sample the move leaves: a pop)."""
    runs = []
    for grow in (False, True):
        pipe = Pipeline(PipelineOptions(samples=6, lookahead=tau, precision="fp32"), criteria=[])
        pipe.criteria.criteria.append(ForcedSwitch(pipe, at=40))
        pipe.set_samples(4)
        out = {}
        for t in range(50):
            if grow and t == 42:
                pipe.set_samples(6)
            pose = pipe.step(take.signals.slice(t, t + 1))
            if pose is not None:
                out[pose.frame] = (pose.positions.copy(), pose.transition)
        assert pipe.samples == (6 if grow else 4) and pipe.switches[0][2:] == (0, 3)
        runs.append(out)
    kept, grown = runs
    move = [f for f in range(36, 43) if kept[f][1]]
    assert len(move) >= 3 and all(grown[f][1] for f in move)
    for f in move:
        np.testing.assert_allclose(grown[f][0], kept[f][0], rtol=0, atol=1e-9)


def test_switch_history_is_bounded_for_long_runs_but_every_switch_is_counted(take, monkeypatch):
    import edge.ssi as ssi_mod
    monkeypatch.setattr(ssi_mod, "SWITCH_HISTORY", 5)

    class CurrentIsWorst:          # makes the shown sample an outlier on every frame
        name, weight = "worst", 1.0

        def cost(self, ctx):
            c = np.zeros(len(ctx.positions))
            c[pipe.current] = 1.0
            return c

    pipe = Pipeline(PipelineOptions(samples=4, lookahead=0, transition=1), criteria=[CurrentIsWorst()])
    for t in range(30):
        pipe.step(take.signals.slice(t, t + 1))
    assert pipe.switch_count == 30 and len(pipe.switches) == 5
    assert [s[0] for s in pipe.switches] == list(range(25, 30))


def _run_pair(take, native, hurt_frame, frames=260, samples=1):
    """A clean pipeline and one whose frames `hurt_frame(t, pipe, sig)` may spoil; their outputs by frame."""
    clean, hurt = Pipeline(PipelineOptions(samples=samples, use_native=native)), Pipeline(PipelineOptions(samples=samples, use_native=native))
    out_clean, out_hurt = {}, {}
    for t in range(frames):
        sig = take.signals.slice(t, t + 1)
        a = clean.step(sig)
        b = hurt.step(hurt_frame(t, hurt, sig))
        if a is not None:
            out_clean[a.frame], out_hurt[b.frame] = a.positions.copy(), b.positions.copy()
            assert np.isfinite(b.positions).all() and np.isfinite(b.rotations).all() and np.isfinite(b.contacts).all()
    err = {f: np.linalg.norm(out_hurt[f] - out_clean[f], axis=-1).mean() for f in out_clean}   # mean joint distance
    return clean, hurt, err


@pytest.mark.parametrize("native", [True, False])
def test_a_hostile_frame_is_refused_at_the_door_and_never_reaches_a_pose(take, native):
    """A headset position of 3e38 (finite, valid on the wire), NaN, or a 1e6 m jump: the frame is
    replaced by the last good one (counted), no NaN reaches a pose, and 60 frames on the output is the
    clean run's again (2 cm mean joint distance; a foot lock taken elsewhere can differ for a step)."""
    from edge.signals import Signals
    bad = {60: 3e38, 61: np.nan, 140: 1e6}

    def spoil(t, pipe, sig):
        return Signals(**{**vars(sig), "head_pos": np.full((1, 3), bad[t])}) if t in bad else sig
    clean, hurt, err = _run_pair(take, native, spoil)
    assert hurt.inputs_held == 3 and clean.inputs_held == 0
    assert _run_pair(take, native, spoil, frames=160, samples=8)[1].inputs_held == 3      # no NaN with SSI either
    assert max(err[f] for f in range(121, 135)) < 0.02 and max(err[f] for f in range(200, 250)) < 0.02


@pytest.mark.parametrize("native", [True, False])
def test_a_blown_up_gru_state_is_reset_and_the_pose_recovers(take, native):
    """What the door cannot catch (a state that goes non-finite by itself): the rows are reset to the
    start-of-clip state, counted, their pose held for the frame, and the output converges back."""
    def blow_up(t, pipe, sig):
        if t == 80:
            pipe.decoder.state[:] = np.nan      # what the next step reads
        return sig
    clean, hurt, err = _run_pair(take, native, blow_up)
    assert hurt.state_resets == 1 and clean.state_resets == 0
    assert max(err[f] for f in range(141, 200)) < 0.02
    assert _run_pair(take, native, blow_up, frames=160, samples=8)[1].state_resets >= 8   # every sample's row


def _turned(sig, hands_deg=0.0, head_deg=0.0):
    """The signals with both controllers rolled about their wrists by hands_deg (about the hand's own x,
    the forearm's axis; the grips move, the wrists stay) and the headset pitched down by head_deg about
    the head joint (the eyes move, the head joint stays)."""
    from dataclasses import replace
    from edge import quat
    from edge.features import head_joint, wrist_joints
    from edge.signals import EYE_OFFSET, GRIP_OFFSET
    roll = quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(hands_deg))
    hand_rot = quat.mul(sig.hand_rot, np.broadcast_to(roll, sig.hand_rot.shape))
    hand_pos = wrist_joints(sig.hand_pos, sig.hand_rot) + quat.rotate(hand_rot, GRIP_OFFSET)
    pitch = quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(head_deg))
    head_rot = quat.mul(sig.head_rot, np.broadcast_to(pitch, sig.head_rot.shape))
    head_pos = head_joint(sig.head_pos, sig.head_rot) + quat.rotate(head_rot, EYE_OFFSET)
    return replace(sig, hand_rot=hand_rot, hand_pos=hand_pos, head_rot=head_rot, head_pos=head_pos)


@pytest.mark.parametrize("native", [True, False])
def test_rolling_a_controller_about_the_wrist_leaves_the_legs_where_they_are(take, native):
    """The decoder's upper-body head reads the controllers' orientations for the collars alone: rolling
    both controllers 60 degrees about the wrists moves the collars and shoulders and not one joint of
    the torso or the legs (int8, as the board runs). Pitching the headset 25 degrees does move the
    neck and chest: the head reads it."""
    from edge.skeleton import JOINT
    pipe = Pipeline(PipelineOptions(samples=1, use_native=native))
    if not pipe.orientations:
        pytest.skip("the shipped decoder reads no orientations")
    legs = [JOINT[n] for n in ("pelvis", "spine", "chest", "neck", "head", "l_hip", "l_knee", "l_ankle", "l_toe",
                               "r_hip", "r_knee", "r_ankle", "r_toe")]
    shoulders = [JOINT[n] for n in ("l_shoulder", "r_shoulder")]
    sig = take.signals.slice(0, 150)

    def run(s):
        pipe.reset()
        return np.stack([pipe.step(s.slice(t, t + 1)).positions.copy() for t in range(s.frames)])
    plain, rolled, nodded = run(sig), run(_turned(sig, hands_deg=60)), run(_turned(sig, head_deg=25))
    np.testing.assert_allclose(rolled[:, legs], plain[:, legs], rtol=0, atol=1e-6)
    assert np.linalg.norm(rolled[:, shoulders] - plain[:, shoulders], axis=-1).max() > 0.003
    chest = [JOINT["neck"], JOINT["chest"]]
    assert np.linalg.norm(nodded[:, chest] - plain[:, chest], axis=-1).max() > 0.01


@pytest.mark.parametrize("native", [True, False])
def test_the_hand_axis_turns_only_the_arms_and_keeps_the_wrists_on_the_controllers(take, native):
    """The elbow swivel (edge.ik.swivel_to_hands) runs after the IK: legs, torso, head and wrists are
    the same with it off, the elbows move."""
    from edge.skeleton import JOINT
    elbows = [JOINT["l_elbow"], JOINT["r_elbow"]]
    same = [j for j in range(len(JOINT)) if j not in elbows]
    on, off = (Pipeline(PipelineOptions(samples=1, use_native=native, elbow_from_hand=g)) for g in (2.0, 0.0))
    moved = []
    for t in range(120):
        a, b = on.step(take.signals.slice(t, t + 1)), off.step(take.signals.slice(t, t + 1))
        assert np.allclose(a.positions[same], b.positions[same], atol=1e-5)
        moved.append(np.linalg.norm(a.positions[elbows] - b.positions[elbows], axis=-1).max())
    assert max(moved) > 0.005
