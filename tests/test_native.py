"""The compiled post-processing core (edge/native) against its numpy references, and the fallback."""
import ctypes
import os
import subprocess
import sys

import numpy as np
import pytest

from edge import native, quat
from edge.ik import ELBOW_FROM_HAND
from edge.inference import Autoencoder
from edge.loading import open_models
from edge.options import PipelineOptions
from edge.frame import LIMB_CHAINS, LIMB_POLES
from edge.pipeline import Pipeline
from edge.plausibility import PlausibilityScorer
from edge.skeleton import ANKLES, HEAD, JOINT, NUM_JOINTS, NUM_PREDICTED, OFFSETS, PARENTS, fk
from motion.takes import from_sample
from tests.conftest import SAMPLE, worn_signals

lib = native.load()
pytestmark = pytest.mark.skipif(lib is None, reason=f"compiled core unavailable: {native.why_unavailable()}")
P64 = np.ascontiguousarray(PARENTS, np.int64)
CHAINS64 = np.ascontiguousarray(LIMB_CHAINS, np.int64)
ANKLES64 = np.ascontiguousarray(ANKLES, np.int64)
A = native.addr
SKELETON = native.Skeleton(J=NUM_JOINTS, head=HEAD, neck=JOINT["neck"], parents=A(P64), chains=A(CHAINS64),
                           ankles=A(ANKLES64), offsets=A(OFFSETS), poles=A(LIMB_POLES))


def random_6d(R, seed):
    """Decoder-like 6D output: near-identity columns with noise, some far from orthonormal."""
    rng = np.random.default_rng(seed)
    r6 = np.tile([1.0, 0, 0, 0, 1.0, 0], (R, NUM_PREDICTED)) + 0.6 * rng.standard_normal((R, NUM_PREDICTED * 6))
    return r6.astype(np.float32)


def random_rotations(shape, seed):
    rng = np.random.default_rng(seed)
    return quat.to_matrix(quat.normalize(rng.standard_normal(shape + (4,))))


def numpy_forward(r6, root_m, anchor):
    R = len(r6)
    loc = np.zeros((R, NUM_JOINTS, 3, 3))
    loc[:, 0] = root_m
    quat.matrix_from_6d(r6.reshape(R, NUM_PREDICTED, 6), out=loc[:, 1:])
    W, P = fk(loc, np.zeros(3))
    P += anchor[..., None, :] - P[:, HEAD:HEAD + 1]
    return loc, W, P


def native_forward(r6, root_m, anchor):
    R = len(r6)
    loc, W, P = np.zeros((R, NUM_JOINTS, 3, 3)), np.zeros((R, NUM_JOINTS, 3, 3)), np.zeros((R, NUM_JOINTS, 3))
    a, sa = native.rows(r6, 1, np.float32)
    b, sb = native.rows(root_m, 2)
    c, sc = native.rows(anchor, 1)
    lib.ep_forward(SKELETON, R, native.ForwardInputs(a, sa, b, sb, c, sc, None, None),
                   native.PoseRows(A(loc), A(W), A(P)))
    return loc, W, P


@pytest.mark.parametrize("shared", [True, False])
def test_forward_matches_numpy_6d_fk_and_head_anchor(shared):
    R = 37
    r6 = random_6d(R, 0)
    root = random_rotations(() if shared else (R,), 1)
    anchor = np.array([0.3, 1.6, -0.2]) if shared else np.random.default_rng(2).normal(0, 1, (R, 3))
    for ref, got in zip(numpy_forward(r6, root, anchor), native_forward(r6, root, anchor), strict=True):
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("swivel", [0.0, ELBOW_FROM_HAND])
def test_limb_ik_matches_numpy_on_reachable_unreachable_and_straight_chains(swivel):
    """ep_post against NumpyFrame.post, with the elbows turned to the hands (edge.ik.swivel_to_hands) and without:
    the random controllers put many beyond reach (edge.ik.shoulders_to_reach) and straight arms' elbows
    in the torso (edge.ik.shoulders_out_of_torso)."""
    R = 64
    rng = np.random.default_rng(3)
    loc, W, P = numpy_forward(random_6d(R, 4), random_rotations((R,), 5), rng.normal(0, 1, (R, 3)))
    loc[:8, [JOINT["l_knee"], JOINT["r_knee"], JOINT["l_elbow"], JOINT["r_elbow"]]] = np.eye(3)   # straight
    W, P = fk(loc, np.zeros((R, 3)))
    ends = P[:, LIMB_CHAINS[:, 2]]
    targets = ends + rng.normal(0, 0.4, (R, len(LIMB_CHAINS), 3))          # some out of reach
    weights = rng.uniform(0, 1, (R, 2))
    weights[:4] = 1.0
    weights[4:6] = 0.0
    hand_m, head_m = random_rotations((R, 2), 6), random_rotations((R,), 7)
    results = []
    # NumpyFrame.post: legs to foot goals, arms onto controllers, head; and ep_post, its C form.
    pipe = Pipeline(PipelineOptions(samples=R, use_native=False, elbow_from_hand=swivel))
    pipe.bufs.local[:R], pipe.bufs.world[:R], pipe.bufs.pos[:R] = loc, W, P
    pipe.bufs.targets[:R], pipe.bufs.weights[:R] = targets[:, :2], weights
    pipe.reference.post(R, targets[:, 2:].copy(), hand_m, head_m)
    results.append([x[:R].copy() for x in (pipe.bufs.local, pipe.bufs.world, pipe.bufs.pos)])
    cl, cw, cp = loc.copy(), W.copy(), P.copy()
    goals, goal_w = np.ascontiguousarray(targets[:, :2]), np.ascontiguousarray(weights)
    wrists = np.ascontiguousarray(targets[:, 2:])     # held: C reads it by address
    wr, wr_s = native.rows(wrists, 2)
    hm, hm_s = native.rows(hand_m, 3)
    hd, hd_s = native.rows(head_m, 2)
    lift = np.zeros((R, 2))
    lib.ep_post(SKELETON, R, native.LimbGoals(A(goals), A(goal_w), 1, 1, wr, wr_s, hm, hm_s, hd, hd_s, A(lift), swivel),
                native.PoseRows(A(cl), A(cw), A(cp)))
    results.append([cl, cw, cp])
    # A straight chain puts acos at +-1, where 1e-16 differences in its argument become 1e-8 in angle.
    for r, g in zip(*results, strict=True):
        np.testing.assert_allclose(g[8:], r[8:], rtol=0, atol=1e-10)
        np.testing.assert_allclose(g[:8], r[:8], rtol=0, atol=1e-6)


def test_matrix_to_quaternion_is_numpys_to_the_bit():
    """ep_from_matrix (the pose stream's quaternions) gives quat.from_matrix's bits: rotations of every
    kind, each of Shepperd's four branches, matrices that are not quite rotations, zeros and NaN."""
    lib = native.load()
    rng = np.random.default_rng(1)
    m = quat.to_matrix(quat.normalize(rng.standard_normal((20000, 4))))
    m[:500] *= 1.0 + 1e-3 * rng.standard_normal((500, 3, 3))
    m[500:510], m[510:520] = np.nan, 0.0
    m[520:530] = np.diag([-1.0, -1.0, 1.0])
    m[530:540] = np.diag([1.0, -1.0, -1.0])
    m = np.ascontiguousarray(m)
    got = np.empty((len(m), 4))
    lib.ep_from_matrix(len(m), native.addr(m), native.addr(got))
    want = quat.from_matrix(m)
    np.testing.assert_array_equal(got, want)            # NaN where numpy has NaN
    assert np.isnan(got[500:510]).all() and np.isfinite(got[510:]).all()


def test_plausibility_score_matches_numpy_and_reuses_its_buffers():
    manifest, _, ae_session = open_models()
    B = 24
    _, W, P = numpy_forward(random_6d(B, 7), random_rotations((B,), 8), np.random.default_rng(9).normal(0, 1, (B, 3)))
    fast = PlausibilityScorer(Autoencoder(ae_session, B), manifest["plausibility_threshold_m"])
    slow = PlausibilityScorer(Autoencoder(ae_session, B), manifest["plausibility_threshold_m"], use_native=False)
    assert fast._native and not slow._native
    got = fast.lower_body_error(P, W[:, 0])           # the pelvis rows are strided, as in the pipeline
    np.testing.assert_allclose(got, slow.lower_body_error(P, W[:, 0]), rtol=0, atol=1e-9)
    assert got.base is fast._err
    # Other batch sizes (whole clips in edge eval) take the numpy path and still agree.
    np.testing.assert_allclose(fast.lower_body_error(P[:5], W[:5, 0]), got[:5], rtol=0, atol=1e-9)


@pytest.mark.parametrize("samples,ssi,ik", [(1, True, "both"), (8, False, "both"), (8, True, "both"),
                                              (8, True, "feet"), (8, True, "arms")])
def test_pipeline_output_is_the_same_with_and_without_the_compiled_core(samples, ssi, ik):
    take = from_sample(SAMPLE)
    sig = worn_signals(take)            # every extra IMU worn, dropping out now and then
    runs = []
    for use_native in (True, False):
        pipe = Pipeline(PipelineOptions(samples=samples, ssi=ssi, use_native=use_native, foot_ik=ik != "arms", arm_ik=ik != "feet"))
        assert (pipe.native is not None) == use_native
        poses = []
        for t in range(400):
            pose = pipe.step(sig.slice(t, t + 1))
            if pose is not None:
                poses.append((pose.positions.copy(), pose.rotations.copy(), pose.sample, pose.contacts.copy()))
        runs.append((poses, list(pipe.switches)))
    (a, sw_a), (b, sw_b) = runs
    assert sw_a == sw_b
    assert [p[2] for p in a] == [p[2] for p in b]
    np.testing.assert_allclose(np.array([p[3] for p in a]), np.array([p[3] for p in b]), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.array([p[0] for p in a]), np.array([p[0] for p in b]), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.array([p[1] for p in a]), np.array([p[1] for p in b]), rtol=0, atol=1e-9)


def test_the_present_frames_pose_kept_from_poses_is_the_one_emit_would_make():
    """At look-ahead 0 ep_frame_poses leaves the shown row's pose (a sample's, or a move's spare row)
    in the output and ep_emit takes it instead of making it again: the stream is bit for bit the one
    made with every pose made again, across moves between samples and a change of N."""
    take = from_sample(SAMPLE)
    runs = []
    for keep in (1, 0):
        pipe = Pipeline(PipelineOptions(samples=8))
        assert pipe.native is not None and pipe.lookahead == 0 and pipe.path.core.contents.keep_shown == 1
        pipe.path.core.contents.keep_shown = keep
        poses = []
        for t in range(360):
            if t == 200:
                pipe.set_samples(5)
            pose = pipe.step(take.signals.slice(t, t + 1))
            poses.append((pose.positions.copy(), pose.rotations.copy(), pose.contacts.copy(), pose.sample,
                          pose.transition))
        runs.append(poses)
    kept, made = runs
    assert len({p[3] for p in kept}) >= 2 and any(p[4] for p in kept)    # samples other than 0, and moves
    assert [p[3:] for p in kept] == [p[3:] for p in made]
    for a, b in zip(kept, made, strict=True):
        for k in range(3):
            np.testing.assert_array_equal(a[k], b[k])


def _python(code, **env):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**os.environ, **env}, cwd=os.path.dirname(os.path.dirname(__file__)))


def test_without_a_compiler_the_pipeline_falls_back_to_numpy_and_says_so(tmp_path):
    code = ("from edge import native; from edge.options import PipelineOptions; from edge.pipeline import Pipeline; p = Pipeline(PipelineOptions(samples=2)); "
            "print('native' if p.native else 'numpy', native.why_unavailable())")
    r = _python(code, CC="/nonexistent/cc", EDGEPOSE_CACHE=str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("numpy") and "no C compiler" in r.stdout
    assert "using numpy" in r.stderr
    r = _python(code, EDGEPOSE_NATIVE="0")
    assert r.stdout.startswith("numpy disabled"), r.stdout + r.stderr


def _unoptimised_builds(monkeypatch, cache):
    """edge.native.build into `cache` at -O0 and without -march: the rebuild tests pin down the cache's
    key, not the code, and an unoptimised build takes 0.4 s against -O3's 4."""
    monkeypatch.setenv("EDGEPOSE_CACHE", str(cache))
    monkeypatch.setattr(native, "CFLAGS", tuple(f for f in native.CFLAGS if not f.startswith("-O")) + ("-O0",))
    monkeypatch.setattr(native, "ARCH_FLAGS", ((),))


def test_a_source_edit_rebuilds_into_a_new_cached_library(tmp_path, monkeypatch):
    _unoptimised_builds(monkeypatch, tmp_path)
    first = native.build()
    assert first.exists() and native.build() == first
    src = tmp_path / "postproc.c"
    src.write_text(native.SOURCE.read_text() + "\n/* edited */\n")
    monkeypatch.setattr(native, "SOURCE", src)
    second = native.build()
    assert second != first and second.exists()


def test_the_constants_shared_with_python_live_in_python_and_a_change_rebuilds(tmp_path, monkeypatch):
    """postproc.c has no copy of the floor limits, rest heights, lock snap and support band: without the
    -D flags edge.native.build derives from edge.physics it does not compile, and a changed value there
    is a new library."""
    import shlex
    from edge import physics
    cc = shlex.split(os.environ.get("CC", "cc"))
    check = cc + ["-fsyntax-only", "-I", str(native.SOURCE.parent), str(native.SOURCE)]
    bare = subprocess.run(check, capture_output=True, text=True)
    assert bare.returncode != 0 and "edge.native.build" in bare.stderr
    defines = [f"-D{k}={float(v)!r}" for k, v in native.shared_constants().items()]
    assert subprocess.run(check + defines, capture_output=True, text=True).returncode == 0
    assert native.shared_constants()["FLOOR_ANKLE"] == physics.FLOOR_ANKLE
    _unoptimised_builds(monkeypatch, tmp_path)
    first = native.build()
    monkeypatch.setattr(physics, "FLOOR_ANKLE", physics.FLOOR_ANKLE + 0.01)
    assert native.build() != first


def test_foot_locks_match_numpy_through_contacts_releases_and_slips():
    from edge.ik import FootLock
    B, T = 16, 300
    rng = np.random.default_rng(10)
    ref, nat = FootLock(B), FootLock(B)
    locks = native.FootLocks(nat.release_frames, nat.max_slip, A(nat.lock_pos), A(nat.since_release), A(nat.weight),
                             A(nat.locked), A(nat.raw), nat.min_gap)
    pos = np.zeros((B, NUM_JOINTS, 3))
    goal = np.zeros((B, 2, 3))
    contacts = np.zeros((B, 2), np.float32)
    walk = np.zeros((B, 2, 3)) + [0, 0.12, 0]
    for t in range(T):
        walk += rng.normal(0, 0.01, walk.shape) + (rng.uniform(size=(B, 2, 1)) < 0.02) * 0.1   # drifts and slips
        pos[:, ANKLES] = walk
        pos[:, ANKLES, 1] = 0.09 + rng.uniform(-0.04, 0.08, (B, 2))          # on, under and above the floor
        drop = np.ascontiguousarray(rng.uniform(-0.1, 0.05, (B, 2)))       # toes below or above their ankles
        contacts[:] = (np.sin(t / 9.0 + np.arange(B)[:, None] + [0, 1.5]) + rng.normal(0, 0.3, (B, 2))) > 0
        lock, w = ref.update(contacts, pos[:, ANKLES], drop)
        want = (lock - pos[:, ANKLES]) * w[..., None] + pos[:, ANKLES]
        lib.ep_foot_locks(SKELETON, B, A(contacts), A(pos), A(drop), locks, A(goal))
        assert np.array_equal(nat.locked, ref.locked) and np.array_equal(nat.raw, ref.raw)
        np.testing.assert_allclose(nat.weight, ref.weight, rtol=0, atol=1e-15)
        np.testing.assert_allclose(goal, want, rtol=0, atol=1e-12)
    assert ref.locked.any() and (~ref.locked).any()


def test_the_leg_guard_in_c_moves_the_goals_numpy_moves_and_survives_legs_on_top_of_each_other():
    """ep_foot_locks with the leg guard on: the goals guard_legs gives after FootLock.update, on legs
    swung about at random (they pass within the clearance often) and on a pose with every joint at one
    point (zero-length segments, no direction apart: the goals stay where they are, finite)."""
    from edge.ik import FootLock, guard_legs
    from edge.physics import LEG_GUARD_M, LEG_GUARD_MAX_PUSH_M, LEG_SEGMENTS
    B, T = 16, 60
    rng = np.random.default_rng(11)
    ref, nat = FootLock(B), FootLock(B)
    locks = native.FootLocks(nat.release_frames, nat.max_slip, A(nat.lock_pos), A(nat.since_release), A(nat.weight),
                             A(nat.locked), A(nat.raw), nat.min_gap, LEG_GUARD_M, LEG_GUARD_MAX_PUSH_M, A(LEG_SEGMENTS))
    goal = np.zeros((B, 2, 3))
    contacts = np.zeros((B, 2), np.float32)
    moved = 0
    for t in range(T):
        local = quat.to_matrix(quat.normalize(np.tile([1.0, 0, 0, 0], (B, NUM_JOINTS, 1))
                                              + 0.25 * rng.standard_normal((B, NUM_JOINTS, 4))))
        _, pos = fk(local, np.zeros((B, 3)) + [0, 0.95, 0])
        if t == T - 1:
            pos[:] = 0.0                                   # every joint at one point
        pos = np.ascontiguousarray(pos)
        contacts[:] = rng.uniform(size=(B, 2)) > 0.5
        lock, w = ref.update(contacts, pos[:, ANKLES])
        want = (lock - pos[:, ANKLES]) * w[..., None] + pos[:, ANKLES]
        before = want.copy()
        guard_legs(pos, want, w)
        moved += int((np.abs(want - before).max(axis=(1, 2)) > 1e-6).sum())
        lib.ep_foot_locks(SKELETON, B, A(contacts), A(pos), None, locks, A(goal))
        assert np.isfinite(goal).all()
        np.testing.assert_allclose(goal, want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(goal, before)            # on top of each other: nothing to push along
    assert moved > B * T / 10


def frame_inputs(pipe, sig, state):
    """ep_frame_features, ep_imu_features and ep_orientation_features (the first half of ep_frame_inputs) on one frame ->
    (body points [4,3], features [n_features] float32, matrices [4,3,3]: waist, hands, head). `state` is
    the caller's dict of the C side's buffers, kept from frame to frame; empty on the first frame."""
    first = not state
    if first:
        state.update(points=np.zeros((4, 3)), prev=np.zeros((4, 3)), feat=np.zeros(pipe.n_features, np.float32),
                     mats=np.zeros((4, 3, 3)))
    pipe._load_frame_in(sig)
    pts, prev, feat, mats = state["points"], state["prev"], state["feat"], state["mats"]
    lib.ep_frame_features(A(pipe.bufs.frame_in), A(pipe.path._frame_offsets), A(pts if first else prev), pipe.fps,
                          A(pts), A(feat), A(mats))
    if pipe.imus:
        lib.ep_imu_features(pipe.imus, A(pipe.bufs.inputs["imu_rot"]), A(pipe.bufs.inputs["imu_flag"]), A(pipe.bufs.inputs["waist_rot"]),
                            feat.ctypes.data + 4 * 24)
    if pipe.orientations:
        lib.ep_orientation_features(A(pipe.bufs.frame_in), feat.ctypes.data + 4 * (24 + 49))
    np.copyto(prev, pts)
    return pts, feat, mats


def test_frame_features_are_bit_identical_to_the_numpy_features_training_used():
    from edge.features import body_points, features, heading, imu_features, orientation_features
    take = from_sample(SAMPLE)
    signals = worn_signals(take)
    pipe = Pipeline(PipelineOptions(samples=1, body_scale=1.07))
    prev, state = None, {}
    for t in range(300):
        sig = signals.slice(t, t + 1)
        points, waist_rot = body_points(sig, 1.07)
        points, waist_rot = points[0], waist_rot[0]
        want = features(points, points if prev is None else prev, heading(waist_rot), 60.0)
        if pipe.imus:
            want = np.concatenate([want, imu_features(sig.imu_rot[0], sig.imu_flag[0], heading(waist_rot))])
        if pipe.orientations:
            want = np.concatenate([want, orientation_features(sig.head_rot[0], sig.hand_rot[0], heading(waist_rot))])
        want = want.astype(np.float32)
        prev = points
        q = np.stack([waist_rot, *sig.hand_rot[0], sig.head_rot[0]])
        got_points, got, mats = frame_inputs(pipe, sig, state)
        assert np.array_equal(got, want), t
        assert np.array_equal(got_points, points)
        assert np.array_equal(mats, quat.to_matrix(q))


def test_switch_decision_matches_is_outlier_and_best_other():
    from edge.ssi import best_other, is_outlier
    rng = np.random.default_rng(11)
    for trial in range(3000):
        N = int(rng.integers(2, 129))
        cost = rng.gamma(2.0, 0.01, N)
        if trial % 3 == 0:
            cost = np.round(cost, 2)            # ties, in the median and at the minimum
        c = int(rng.integers(N))
        if trial % 5 == 0:
            cost[c] += rng.uniform(0, 0.1)      # often an outlier
        margin = (0.0, 0.02, 0.05)[trial % 3]
        want = best_other(cost, c) if is_outlier(cost, c, margin) else -1
        assert lib.ep_switch_to(N, A(cost), c, margin) == want, (N, c, margin)
    nan = np.array([0.1, np.nan, 5.0, 0.2])
    assert not is_outlier(nan, 2) and lib.ep_switch_to(4, A(nan), 2, 0.0) == -1


def test_a_decoder_swapped_in_after_construction_is_the_one_the_compiled_core_reads():
    """bench/reference.py swaps in a PyTorch decoder; the C calls must follow (not the freed buffers)."""
    from edge.inference import Decoder
    take = from_sample(SAMPLE)
    plain, swapped = Pipeline(PipelineOptions(samples=4, precision="fp32")), Pipeline(PipelineOptions(samples=4, precision="fp32"))
    m = swapped.manifest
    swapped.decoder = Decoder(swapped.decoder.session, swapped.rows, m["latent"], m["hidden"], m["features"])
    swapped.decoder.latent[:4] = swapped.latents
    for t in range(60):
        a, b = plain.step(take.signals.slice(t, t + 1)), swapped.step(take.signals.slice(t, t + 1))
        if a is not None:
            assert np.array_equal(a.positions, b.positions)


def test_the_live_frame_inputs_land_in_the_ring_bit_identical_to_the_numpy_path():
    take = from_sample(SAMPLE)
    sig = worn_signals(take)
    pipes = [Pipeline(PipelineOptions(samples=8, use_native=u, precision="fp32")) for u in (True, False)]
    for t in range(40):
        for p in pipes:
            p.step(sig.slice(t, t + 1))
        a, b = (p.buffer for p in pipes)
        for k in ("features", "anchor", "wrists", "waist_m", "hand_m", "head_m", "hidden_in", "seg_flag"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), k
        np.testing.assert_allclose(a.seg_m, b.seg_m, rtol=0, atol=1e-14)     # the torso's midway rotations
        assert np.array_equal(pipes[0].decoder.features, pipes[1].decoder.features)


def test_the_ctypes_mirrors_match_the_c_structs_and_a_mismatch_refuses_to_load(monkeypatch):
    """postproc.c reports its structs' sizes and core_context's field offsets (ep_layout); the loader
    compares them with the ctypes mirrors and, if one was edited on one side only, says which."""
    assert native.layout_mismatch(lib) == ""

    class Shifted(ctypes.Structure):      # the mirror with one field's type changed (an int widened to a double)
        _fields_ = [(n, ctypes.c_double if n == "foot_ik" else t) for n, t in native.CoreContext._fields_]
    monkeypatch.setattr(native, "CoreContext", Shifted)
    assert "CoreContext.arm_ik" in native.layout_mismatch(lib)


def test_arrays_crossing_into_c_are_checked_for_dtype_layout_and_shape():
    a = np.zeros((4, 3))
    assert native.checked_addr(a, np.float64, (None, 3)) == a.ctypes.data
    with pytest.raises(TypeError, match="float64"):
        native.checked_addr(a.astype(np.float32), np.float64)
    with pytest.raises(ValueError, match="contiguous"):
        native.checked_addr(a[:, :2], np.float64)
    with pytest.raises(ValueError, match="shape"):
        native.checked_addr(a, np.float64, (4, 2))


def test_a_public_call_with_arrays_c_cannot_take_gets_the_numpy_answer():
    """PlausibilityScorer.lower_body_error is public: float32 or strided positions must not reach C as
    if they were contiguous float64 (garbage, or a crash); they take the numpy path and agree."""
    manifest, _, ae_session = open_models()
    B = 4
    scorer = PlausibilityScorer(Autoencoder(ae_session, B), manifest["plausibility_threshold_m"])
    _, W, P = numpy_forward(random_6d(B, 11), random_rotations((B,), 12), np.random.default_rng(13).normal(0, 1, (B, 3)))
    want = scorer.lower_body_error(P, W[:, 0]).copy()
    np.testing.assert_allclose(scorer.lower_body_error(P.astype(np.float32), W[:, 0]), want, atol=1e-4)
    strided = np.zeros((B, NUM_JOINTS, 6))
    strided[..., ::2] = P
    np.testing.assert_allclose(scorer.lower_body_error(strided[..., ::2], W[:, 0]), want, atol=1e-9)
