"""Latent refinement (edge.refine): its Jacobian, reaching a target, refusing a bad one, dropping a
lost tracker's term, and changing nothing when no constraint is live."""
import numpy as np
import pytest

from edge.imus import IMU_JOINTS
from edge.inference import Decoder, JacobianBatch
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.refine import ImuOrientation, RefineContext, TargetReach
from edge.skeleton import JOINT, NUM_JOINTS
from motion.evaluate import run_take
from motion.takes import from_sample
from tests.conftest import SAMPLE

L_TOE = JOINT["l_toe"]


@pytest.fixture(scope="module")
def take():
    return from_sample(SAMPLE)


def run_to(pipe, take, frame):
    pipe.reset()
    for t in range(frame + 1):
        pipe.step(take.signals.slice(t, t + 1))


def lifted_toe_target(take, frame, up=0.35, forward=0.25):
    """A point well above and ahead of where the plain model puts the left toe at `frame` (a kick it
    does not make by itself), and that distance."""
    base = run_take(Pipeline(PipelineOptions(samples=1, precision="fp32")), take, max_frames=frame + 1).pred[frame, L_TOE]
    return base + np.array([0.0, up, forward]), np.hypot(up, forward)


def test_the_jacobian_matches_central_differences(take):
    """refine's forward-difference Jacobian of the live terms (one batched decode) agrees with central
    differences of the residuals taken one latent at a time (fp32, where both are exact to rounding)."""
    pipe = Pipeline(PipelineOptions(samples=1, precision="fp32", refine={"steps": 1, "ik_pull": 0.0}))
    goal, _ = lifted_toe_target(take, 60)
    pipe.refiner.add_target(L_TOE, goal, radius=0.0, first=50, last=60, pelvis=None)
    run_to(pipe, take, 55)                       # refine ran this frame: the batch holds its inputs
    r = pipe.refiner
    z = pipe.decoder.latent[0].astype(np.float64)
    # float32 rounding over h against truncation ~h: with the upper-body head (v0.5) the rounding floor
    # rose (0.14 of the scale at h = 1e-3, 0.052 at 3e-3, 0.038 at 5e-3)
    h = 5e-3
    r0, J = r.jacobian(z, eps=h)
    central = np.stack([(r.residuals_at(z + h * e) - r.residuals_at(z - h * e)) / (2 * h) for e in np.eye(r.L)])
    assert np.abs(r0 - r.residuals_at(z)).max() < 1e-6
    scale = np.abs(central).max()
    assert scale > 1e-3, "the target term must depend on the latent"
    assert np.abs(J - central).max() < 0.05 * scale


def test_the_jacobian_graph_decodes_each_latent_as_the_decoder_does(take):
    """The refiner's batch graph (models.nets.JacobianStep: one frame's features and GRU state shared
    by every row) gives each latent the rotations the decoder step gives it (fp32), and the pipeline's
    refiner runs on it when the models have it."""
    pipe = Pipeline(PipelineOptions(samples=1, precision="fp32", refine=True))
    run_to(pipe, take, 80)
    dec, m = pipe.decoder, pipe.manifest
    batch = pipe.refiner.batch
    assert isinstance(batch, JacobianBatch)
    rng = np.random.default_rng(3)
    latents = (dec.latent[0] + rng.standard_normal((batch.rows, m["latent"]))).astype(np.float32)
    one = Decoder(dec.session, batch.rows, m["latent"], m["hidden"], m["features"], recurrent=False)
    one.features[:], one.hidden[0][:], one.latent[:] = dec.features[0], dec.state[0], latents
    batch.features[:], batch.hidden[0][:], batch.latent[:] = dec.features[0], dec.state[0], latents
    one.step()
    batch.step()
    # the comparison means something only if the latents make different poses (far above its 1e-5)
    assert np.abs(one.rot6d - one.rot6d[0]).max() > 0.02, "the latents must make different poses"
    np.testing.assert_allclose(batch.rot6d, one.rot6d, rtol=0, atol=1e-5)


def test_a_wrong_graph_as_the_jacobian_fails_at_start_up_with_the_fix():
    """A file in the Jacobian's place that is not JacobianStep (here the decoder step: three outputs) is
    refused when the refiner is built, saying how to make the right one."""
    from edge.loading import open_models
    from edge.modelfiles import ModelError
    m, decoder, _ = open_models(precision="fp32")
    with pytest.raises(ModelError, match="jacobian-only"):
        JacobianBatch(decoder, 32, m["latent"], m["hidden"], m["features"])


def test_models_without_the_jacobian_graph_refine_with_the_decoder(tmp_path):
    """An older model folder (no decoder_jacobian.onnx in its manifest) still refines, on the decoder's graph."""
    import json
    import shutil
    from edge.modelfiles import DEFAULT_DIR
    for f in ("decoder.onnx", "autoencoder.onnx", "manifest.json"):
        shutil.copyfile(DEFAULT_DIR / f, tmp_path / f)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["files"] = {k: v for k, v in manifest["files"].items() if k in ("decoder.onnx", "autoencoder.onnx")}
    manifest.pop("precisions", None)
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    pipe = Pipeline(PipelineOptions(samples=1, precision="fp32", refine=True), models=tmp_path)
    assert isinstance(pipe.refiner.batch, Decoder)


@pytest.mark.parametrize("ik_pull", [0.0, 1.0])
def test_a_target_the_model_misses_is_reached(take, ik_pull):
    """A point 43 cm above and ahead of where the plain model puts the left toe mid-walk: refining the
    latent alone (ik_pull 0) takes the toe at least 30 % of the way by the end of the window (the
    model's latent space reaches so far in a walk); with the leg IK's full pull, within 5 cm."""
    frame = 100
    goal, far = lifted_toe_target(take, frame)
    plain = run_take(Pipeline(PipelineOptions(samples=1)), take, max_frames=frame + 1).pred[frame, L_TOE]
    pipe = Pipeline(PipelineOptions(samples=1, refine={"ik_pull": ik_pull}))
    assert pipe.refiner.add_target("l_toe", goal, radius=0.02, first=frame - 20, last=frame) is not None
    got = run_take(pipe, take, max_frames=frame + 1).pred[frame, L_TOE]
    assert np.linalg.norm(plain - goal) > 0.9 * far
    assert np.linalg.norm(got - goal) < (0.7 * far if ik_pull == 0 else 0.05)


@pytest.mark.parametrize("position, joint, why", [
    ([np.nan, 1.0, 0.0], "l_toe", "non_finite"),
    ([0.0, np.inf, 0.0], "l_toe", "non_finite"),
    ([0.0, 1.0, 0.0], "l_tail", "unknown_joint"),
    ([0.0, 1.0, 0.0], 99, "unknown_joint"),
    ([0.0, 1.0, 2.0], "l_toe", "out_of_reach"),
])
def test_a_bad_target_is_refused_counted_and_never_applied(take, position, joint, why):
    pipe = Pipeline(PipelineOptions(samples=1, refine=True))
    assert pipe.refiner.add_target(joint, position, pelvis=np.array([0.0, 1.0, 0.0]), first=0, last=200) is None
    assert pipe.refiner.refused[why] == 1 and sum(pipe.refiner.refused.values()) == 1
    assert pipe.refiner.term("targets").targets == []
    got = run_take(pipe, take, max_frames=120).pred
    want = run_take(Pipeline(PipelineOptions(samples=1, refine=True)), take, max_frames=120).pred   # no target asked
    assert np.array_equal(got, want)


def test_an_imu_term_drops_when_its_tracker_is_lost():
    """ImuOrientation has 9 residuals per worn IMU, weighted by its flag; an IMU whose flag is 0
    (unplugged, or faded out) has none, and with none worn the term is not live."""
    ctx = RefineContext()
    ctx.seg_m = np.tile(np.eye(3), (NUM_JOINTS, 1, 1))
    ctx.seg_flag = np.zeros(NUM_JOINTS)
    ctx.raw_world = np.tile(np.eye(3), (4, NUM_JOINTS, 1, 1))
    ctx.raw_world[:, :, 0, 1] = 0.1
    term = ImuOrientation()
    ctx.seg_flag[IMU_JOINTS[[1, 3]]] = 1.0
    assert term.size(ctx) == 18 and term.residuals(ctx).shape == (4, 18)
    ctx.seg_flag[IMU_JOINTS[3]] = 0.0              # lost on this frame
    assert term.size(ctx) == 9 and np.abs(term.residuals(ctx)).max() > 0
    ctx.seg_flag[IMU_JOINTS[1]] = 0.0
    assert term.size(ctx) == 0


def test_a_target_term_is_live_only_in_its_window():
    reach = TargetReach()
    ctx = RefineContext()
    reach.targets.append(__import__("edge.refine").refine.Target(L_TOE, np.zeros(3), first=10, last=20))
    for frame, live in ((9, 0), (10, 3), (20, 3), (21, 0)):
        ctx.frame = frame
        assert reach.size(ctx) == live


def test_live_targets_are_one_list_until_a_window_opens_or_closes_or_the_targets_change():
    """TargetReach.live keeps its answer between window edges (a refined frame makes no new list, and
    the refiner redoes its masks only when it changes), and sees a target added or dropped at once."""
    from edge.refine import Target
    reach = TargetReach()
    a = Target(L_TOE, np.zeros(3), first=10, last=20)
    reach.targets.append(a)
    assert reach.live(9) == []
    at_10 = reach.live(10)
    assert at_10 == [a] and reach.live(15) is at_10 and reach.live(20) is at_10
    b = Target(L_TOE, np.ones(3), first=0, last=30)
    reach.targets.append(b)                                    # added mid-window
    assert reach.live(15) == [a, b]
    assert reach.live(21) == [b]                               # a's window closed
    reach.targets = [a]                                        # b dropped (as remove_target does)
    assert reach.live(21) == [] and reach.live(12) == [a]      # and a frame before (a reset)


@pytest.mark.parametrize("samples", [1, 8])
def test_without_a_live_constraint_the_refiner_changes_nothing(take, samples):
    """4-point input, no target and no LegsApart: every output pose is bit for bit the unrefined
    pipeline's (the guards never move the latent alone)."""
    guards = {"terms": ("targets", "keep", "floor")}
    got = run_take(Pipeline(PipelineOptions(samples=samples, refine=guards)), take, max_frames=240).pred
    want = run_take(Pipeline(PipelineOptions(samples=samples)), take, max_frames=240).pred
    assert np.array_equal(got, want)


@pytest.mark.skipif(not __import__("edge.native").native.load(), reason="needs the compiled core")
def test_the_compiled_step_holds_the_shown_rows_planted_feet(take):
    """With sample 3 shown at N=8, the compiled step reads row 3's foot locks from FootLock's state (as
    the numpy step reads the row's views): a lock moved 7 cm on that row alone costs both the same."""
    # ssi=False: the shown row stays 3 (a switch would move the step to another row)
    pipe = Pipeline(PipelineOptions(samples=8, precision="fp32", ssi=False, refine={"steps": 1, "terms": ["targets", "keep", "floor"]}))
    goal, _ = lifted_toe_target(take, 60)
    pipe.reset()
    pipe.switcher.current = 3
    pipe.refiner.add_target(L_TOE, goal, radius=0.02, first=40, last=60)
    for t in range(56):
        pipe.step(take.signals.slice(t, t + 1))
    r, feet = pipe.refiner, pipe.feet
    assert pipe.switcher.current == 3 and r._c_on
    feet.weight[:] = 0.0                          # only the shown row's locks hold
    feet.weight[3] = 1.0
    feet.lock_pos[3] += [0.05, 0.0, 0.05]
    z0 = pipe.decoder.latent[3].astype(np.float64)
    zp = pipe.latents[3].astype(np.float64)
    cost_c = r.step(z0.copy(), z0, zp)
    r._c_on = False
    cost_n = r.step(z0.copy(), z0, zp)
    assert abs(cost_c - cost_n) <= 1e-6 * cost_n


def test_at_zero_steps_a_live_target_moves_no_latent_and_a_moved_one_is_let_go(take):
    """The governor's K = 0 rung (Pipeline.set_refine_steps): the target stays live but the latent is
    the sample's own again within a few frames; at K = 2 it had moved."""
    pipe = Pipeline(PipelineOptions(samples=1, precision="fp32", refine={"steps": 2, "ik_pull": 0.0}))
    goal, _ = lifted_toe_target(take, 100)
    pipe.refiner.add_target(L_TOE, goal, radius=0.0, first=40, last=200)
    run_to(pipe, take, 60)
    assert np.abs(pipe.decoder.latent[0] - pipe.latents[0]).max() > 0.1
    pipe.set_refine_steps(0)
    for t in range(61, 120):
        pipe.step(take.signals.slice(t, t + 1))
    assert pipe.refiner.term("targets").live(pipe.t), "the target is still live"
    np.testing.assert_array_equal(pipe.decoder.latent[0], pipe.latents[0])


def test_the_latent_lets_go_after_the_window_and_the_pose_returns(take):
    """After a target's window the refined latent eases back to the sample's own (0.1 s time
    constant) and the latent is the sample's again; the GRU state forgets the refined frames more
    slowly (and a foot lock taken meanwhile holds where it was taken): 2 s on, the pose is the
    unrefined one to 3 mm on average and 2 cm at most on 95 % of the frames (a discrete foot-lock or
    leg-guard decision may still go the other way for a frame: with v0.4.1, the right knee 10 cm on
    one frame of 30)."""
    frame = 100
    goal, _ = lifted_toe_target(take, frame)
    pipe = Pipeline(PipelineOptions(samples=1, refine={"terms": ["targets", "keep", "floor"]}))   # the target's alone
    pipe.refiner.add_target("l_toe", goal, first=frame - 20, last=frame)
    got = run_take(pipe, take, max_frames=frame + 150).pred
    want = run_take(Pipeline(PipelineOptions(samples=1)), take, max_frames=frame + 150).pred
    assert np.abs(got[frame] - want[frame]).max() > 0.1
    late = np.linalg.norm(got[frame + 120:] - want[frame + 120:], axis=-1)
    assert late.mean() < 3e-3 and np.percentile(late.max(-1), 95) < 0.02
    assert np.array_equal(pipe.decoder.latent[0], pipe.latents[0])


@pytest.mark.skipif(not __import__("edge.native").native.load(), reason="needs the compiled core")
@pytest.mark.parametrize("imus, legs", [("none", False), ("all seven", False), ("none", True)])
def test_the_compiled_step_is_the_numpy_step(take, imus, legs):
    """ep_refine_step (FK in float32 with the worn IMUs' segments, the targets, keep, floor and legs
    residuals, the Jacobian and the Cholesky solve in C) moves the latent where the numpy step does,
    from the same batch (to 1 % of the step)."""
    from dataclasses import replace
    from edge.imus import IMU_LOCATIONS, ImuNoise, mask
    from motion.synth import wear
    if imus != "none":
        take = replace(take, signals=wear(take.signals, mask(IMU_LOCATIONS), take.fps, np.random.default_rng(0),
                                          ImuNoise()))
    terms = ["targets", "keep", "floor"] + (["legs"] if legs else [])
    pipe = Pipeline(PipelineOptions(samples=1, precision="fp32", refine={"steps": 1, "terms": terms}))
    goal, _ = lifted_toe_target(take, 60)
    pipe.refiner.add_target(L_TOE, goal, radius=0.02, first=40, last=60)
    run_to(pipe, take, 55)
    r = pipe.refiner
    if legs:            # armed, at a clearance every frame's legs are inside (the hips are 18 cm apart)
        lg = r.term("legs")
        lg.armed, lg.clearance = True, 0.30
        r._terms = r.live_terms(r.ctx)
        r._c_on = r._prepare_compiled(r._terms)
        assert lg in r._terms
    assert r._c_on, "this frame's terms are all the compiled step's"
    assert (pipe.buffer.seg_flag[pipe.buffer.slot(pipe.t)] > 0).any() == (imus != "none")   # segments set
    z0 = pipe.decoder.latent[0].astype(np.float64) + 0.1
    zp = pipe.latents[0].astype(np.float64)
    compiled, numpy_ = z0.copy(), z0.copy()
    cost_c = r.step(compiled, z0, zp)
    r._c_on = False
    cost_n = r.step(numpy_, z0, zp)
    # the compiled step's FK runs in float32 (the numpy step's in float64): 1e-7 of a position
    assert abs(cost_c - cost_n) <= 1e-6 * max(cost_n, 1e-12)
    assert np.abs(compiled - z0).max() > 1e-3
    assert np.abs(compiled - numpy_).max() <= 0.01 * np.abs(numpy_ - z0).max()


def test_the_compiled_batch_fill_is_numpys_to_the_bit(take):
    """ep_refine_fill (the refiner's own latent into the batch's first L + 1 rows, then its steps along
    each axis) writes the bits Refiner._fill_batch writes: z rounded to float32, steps added in float32."""
    pipe = Pipeline(PipelineOptions(samples=1, refine={"steps": 1}))
    r = pipe.refiner
    assert r._c is not None
    L = r.L
    r.z[:] = np.random.default_rng(3).standard_normal(L) * 1.7
    r._c[0].ep_refine_fill(*r._fill_args)
    compiled = r.batch.latent[:L + 1].copy()
    r.batch.latent[:] = 0.0
    r._fill_batch(r.z, r._steps)
    np.testing.assert_array_equal(compiled, r.batch.latent[:L + 1])
    assert np.abs(np.diag(compiled[1:] - compiled[0])).min() > 0      # each row steps along its axis


def crossed_frames(pred):
    from edge.physics import INTERSECT_M, leg_gap
    return int((leg_gap(pred) < INTERSECT_M).sum())


def test_legs_apart_keeps_crossing_legs_apart_and_costs_nothing_while_they_are(take):
    """LegsApart: on the bundled walk, whose N=1 legs pass inside 10 cm of each other in 38 frames,
    at a 20 cm clearance no frame's legs cross (at the shipped 14 cm, chosen on val for mpjpe, fewer
    than without it); the refiner runs only on frames whose shown legs came close with a foot free
    (armed), and until the first of them the output is the unrefined one to the bit. The foot IK's
    leg guard is off here: it would take the crossings away before the latent had to."""
    plain = run_take(Pipeline(PipelineOptions(samples=1, leg_guard=0.0)), take).pred
    assert crossed_frames(plain) >= 10, "the take should have crossings for this test to mean anything"
    shipped = run_take(Pipeline(PipelineOptions(samples=1, refine=True, leg_guard=0.0)), take).pred
    assert crossed_frames(shipped) < crossed_frames(plain)
    pipe = Pipeline(PipelineOptions(samples=1, refine=True, leg_guard=0.0))
    pipe.refiner.term("legs").clearance = 0.20
    got = run_take(pipe, take).pred
    assert crossed_frames(got) == 0
    assert 0 < pipe.refiner.applied < 0.25 * len(got)
    first = int(np.argmax(np.abs(got - plain).max(axis=(1, 2)) > 0))
    assert first > 10 and np.array_equal(got[:first], plain[:first])


def test_legs_apart_is_not_armed_while_both_feet_are_planted():
    """Two planted feet are where their locks hold them: the latent cannot move them apart, so the
    term does not arm (and the refiner does not run) however close the legs are."""
    from edge.refine import LegsApart
    from edge.skeleton import NUM_JOINTS
    lg = LegsApart()
    lg.watch(np.zeros((1, NUM_JOINTS, 3)))      # every joint at one point: the legs on top of each other
    lg.arm(0, np.array([1.0, 1.0]))
    assert not lg.armed
    lg.arm(0, np.array([1.0, 0.3]))
    assert lg.armed


@pytest.mark.skipif(not __import__("edge.native").native.load(), reason="needs the compiled core")
def test_the_compiled_steps_keep_mask_follows_legs_apart_arming(take):
    """While LegsApart moves the legs, KeepPose lets them go, in the compiled step's copy of the mask as
    in the numpy one, frame by frame, as the term arms and disarms (at 20 cm it does often on the walk)
    within a hand target's window (the live targets stay the same while the mask changes)."""
    pipe = Pipeline(PipelineOptions(samples=1, refine=True))
    r = pipe.refiner
    r.term("legs").clearance = 0.20
    pipe.reset()
    wrist = take.signals.hand_pos[200, 0] + np.array([0.0, 0.3, 0.0])
    assert r.add_target("l_wrist", wrist, radius=0.02, first=0, last=400) is not None
    seen, applied = set(), 0
    for t in range(400):
        pipe.step(take.signals.slice(t, t + 1))
        if r.applied > applied and r._c_on:         # the compiled step ran this frame
            assert np.array_equal(r._c_buf["keep"].astype(bool), r.ctx.keep)
            seen.add(bool(r._legs_kept))
        applied = r.applied
    assert seen == {False, True}, "LegsApart should arm and disarm during the window"
