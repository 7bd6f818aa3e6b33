"""A user's legs (#54 item 3): the pose sent on the user's skeleton, hung from the head, the wrists still
on the controllers and no foot under the floor."""
import numpy as np
import pytest

from edge.options import PipelineOptions
from edge.physics import FLOOR_ANKLE, FLOOR_TOE
from edge.pipeline import Pipeline
from edge.proportions import ARM_BONES, LEG_BONES, UserBody, arms_for, legs_for, proportioned_offsets
from edge.skeleton import ANKLES, HEAD, JOINT, OFFSETS, PARENTS, TOES, fk
from motion.takes import from_sample
from tests.conftest import SAMPLE

WRISTS = [JOINT["l_wrist"], JOINT["r_wrist"]]


@pytest.fixture(scope="module")
def poses():
    """Copies of the runtime's poses over a walk and its crouches (the bundled sample), N = 1."""
    sig = from_sample(SAMPLE).signals
    pipe = Pipeline(PipelineOptions(samples=1))
    out = []
    for t in range(0, 240):
        p = pipe.step(sig.slice(t, t + 1))
        out.append((p.positions.copy(), p.rotations.copy(), p.contacts.copy(), p.frame))
    return out


def as_pose(row):
    from edge.frame import Pose
    pos, rot, contacts, frame = row
    return Pose(frame, pos.copy(), rot.copy(), contacts.copy())


def bone_lengths(pos):
    return np.linalg.norm(pos[1:] - pos[PARENTS[1:]], axis=-1)


def test_the_canonical_body_sends_the_pose_untouched(poses):
    pose = as_pose(poses[100])
    assert UserBody(1.0).on_user(pose) is pose


@pytest.mark.parametrize("legs,arms", [(0.92, 1.0), (1.08, 1.0), (1.0, 0.92), (1.05, 1.08)])
def test_limbs_long_or_short_are_sent_that_long_from_the_head_with_the_wrists_on_the_controllers(poses, legs, arms):
    body = UserBody(legs, arms)
    want = bone_lengths(np.asarray(fk(np.eye(3)[None].repeat(len(OFFSETS), 0), np.zeros(3),
                                      offsets=proportioned_offsets(legs, arms))[1]))
    for row in poses[60::30]:
        pose = as_pose(row)
        out = body.on_user(pose)
        got = out.positions
        np.testing.assert_allclose(bone_lengths(got), want, atol=1e-6)          # every bone the user's
        np.testing.assert_allclose(got[HEAD], pose.positions[HEAD], atol=1e-9)  # hung from the tracked head
        np.testing.assert_allclose(got[WRISTS], pose.positions[WRISTS], atol=2e-3)      # on the controllers
        assert (got[ANKLES, 1] >= FLOOR_ANKLE - 1e-6).all() and (got[TOES, 1] >= FLOOR_TOE - 1e-6).all()
        # the hands as the controllers turned them: their world orientation unchanged
        world = fk(out.rotations, got[0], offsets=body.offsets)[0]
        canon = fk(pose.rotations, pose.positions[0])[0]
        np.testing.assert_allclose(world[WRISTS], canon[WRISTS], atol=1e-5)
    thigh_shin = lambda off: sum(np.linalg.norm(off[j]) for j in LEG_BONES[1:3])   # noqa: E731
    assert thigh_shin(body.offsets) == pytest.approx(legs * thigh_shin(OFFSETS))
    upper_fore = lambda off: sum(np.linalg.norm(off[j]) for j in ARM_BONES[:2])     # noqa: E731
    assert upper_fore(body.offsets) == pytest.approx(arms * upper_fore(OFFSETS))


def test_a_limb_length_outside_five_deviations_is_refused():
    with pytest.raises(ValueError, match="legs 1.3 .* 0.8 to 1.2"):
        UserBody(1.3)
    with pytest.raises(ValueError, match="arms 0.7 .* 0.8 to 1.2"):
        UserBody(1.0, 0.7)


def test_an_arm_measured_in_the_t_pose_gives_the_arms_it_came_from():
    from edge.calibration import CANONICAL_ARM
    assert arms_for(CANONICAL_ARM * 1.08 / 0.9, 0.9) == pytest.approx(1.08)


def test_a_measured_leg_length_gives_the_legs_it_came_from():
    """legs_for inverts the skeleton: the hip joint's height standing on a body with those legs, at the
    user's size, reads back as those legs."""
    from edge.skeleton import rest_positions, TOE_HEIGHT
    for legs, scale in ((0.92, 1.2), (1.0, 1.0), (1.08, 0.9)):
        rest = rest_positions(proportioned_offsets(legs))
        hip_height_canonical = TOE_HEIGHT + rest[JOINT["l_hip"], 1] - rest[JOINT["l_toe"], 1]
        assert legs_for(hip_height_canonical / scale, scale) == pytest.approx(legs, abs=1e-9)


def test_long_legs_under_a_trunk_bent_over_are_lifted_onto_the_floor():
    """Bent over at the spine with the legs straight, the shorter trunk no longer lifts the pelvis by
    what the longer legs add: the feet would go under the floor, and are lifted onto it."""
    from edge import quat
    from edge.frame import Pose
    from edge.skeleton import TOE_HEIGHT
    local = np.tile(np.eye(3), (len(OFFSETS), 1, 1))
    local[JOINT["spine"]] = quat.to_matrix(quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(80)))
    _, pos = fk(local, np.zeros(3))
    pos[:, 1] += TOE_HEIGHT - pos[TOES, 1].min()            # standing on the floor
    pose = Pose(0, pos, local, np.ones(2))
    body = UserBody(1.08)
    straight = fk(local, np.zeros(3), offsets=body.offsets)[1]
    straight += pos[HEAD] - straight[HEAD]
    assert straight[TOES, 1].min() < FLOOR_TOE - 0.03        # hung from the head alone: under the floor
    out = body.on_user(pose).positions
    assert (out[ANKLES, 1] >= FLOOR_ANKLE - 1e-6).all() and (out[TOES, 1] >= FLOOR_TOE - 1e-6).all()
    np.testing.assert_allclose(out[HEAD], pos[HEAD], atol=1e-9)
    want = bone_lengths(fk(np.tile(np.eye(3), (len(OFFSETS), 1, 1)), np.zeros(3), offsets=body.offsets)[1])
    np.testing.assert_allclose(bone_lengths(out), want, atol=1e-9)             # the toes moved with their feet
    world = fk(body.pose.rotations, out[0], offsets=body.offsets)
    np.testing.assert_allclose(world[1], out, atol=1e-9)                        # the pose is its rotations' FK


def test_a_board_told_the_users_legs_records_its_bvh_on_them(tmp_path):
    """[body] leg_length_m in the board's config: the BVH's skeleton has the user's legs at the user's
    size, and its frames are the poses on them (the head where the canonical pose put it)."""
    from edge.proportions import CANONICAL_HIP_HEIGHT
    from edgetools.profile import Feeder
    from firmware_bridge import config as config_mod
    from firmware_bridge.service import Service
    from motion import bvh as bvh_file
    feeder = Feeder(60.0, f"legs-{id(tmp_path)}")
    headset, waist = feeder.urls()
    path = tmp_path / "legs.bvh"
    raw = {"headset": {"url": headset}, "trackers": [{"url": waist}], "output": {"pose_stream": "headset", "bvh": str(path)},
           "runtime": {"samples": 1, "precision": "int8"}, "refine": {"enabled": False}, "body": {"height_m": 1.75}}
    probe = Service(config_mod.from_dict(raw, "legs"), clock=lambda: feeder.now, status=None, threaded=False)
    scale = probe.calibration.height_scale
    probe.close()
    raw["body"]["leg_length_m"] = round(1.07 * CANONICAL_HIP_HEIGHT / scale, 4)
    svc = Service(config_mod.from_dict(raw, "legs"), clock=lambda: feeder.now, status=None, threaded=False)
    try:
        assert 1.06 < svc.outputs.body.legs < 1.09
        for k in range(90):
            svc.step(feeder.frame(k))
    finally:
        svc.close()
        feeder.close()
    clip = bvh_file.load(path)
    named = {n: clip.offsets[i] / 100.0 for i, n in enumerate(clip.names) if n in JOINT}
    for joint in ("l_knee", "l_ankle", "spine", "r_elbow"):
        np.testing.assert_allclose(named[joint], svc.outputs.body.offsets[JOINT[joint]] / scale, atol=1e-4)
    assert clip.positions.shape[0] > 60
    np.testing.assert_allclose(clip.positions[-1, 0] / 100.0, svc.outputs.body.pose.positions[0] / scale, atol=1e-4)


def bent_over_pose():
    """Bent over at the spine, legs straight, standing on the floor: longer legs push this one's feet
    under the floor (the pose test_long_legs_under_a_trunk_bent_over_are_lifted_onto_the_floor uses)."""
    from edge import quat
    from edge.frame import Pose
    from edge.skeleton import TOE_HEIGHT
    local = np.tile(np.eye(3), (len(OFFSETS), 1, 1))
    local[JOINT["spine"]] = quat.to_matrix(quat.from_axis_angle(np.array([1.0, 0, 0]), np.radians(80)))
    _, pos = fk(local, np.zeros(3))
    pos[:, 1] += TOE_HEIGHT - pos[TOES, 1].min()
    return Pose(0, pos, local, np.ones(2))


needs_native = pytest.mark.skipif(not __import__("edge.native").native.load(),
                                  reason="the compiled core is the board's frame")


@needs_native
@pytest.mark.parametrize("legs,arms", [(0.92, 1.0), (1.08, 1.0), (1.0, 0.92), (1.05, 1.08), (1.15, 0.85)])
def test_the_compiled_user_body_is_numpys_on_every_body_walking_crouching_and_lifted(poses, legs, arms):
    compiled, reference = UserBody(legs, arms), UserBody(legs, arms, compiled=False)
    assert compiled._lib is not None and reference._lib is None
    rows = [as_pose(r) for r in poses[::7]] + [bent_over_pose()]
    for pose in rows:
        want = reference.on_user(pose)
        want_pos, want_rot = want.positions.copy(), want.rotations.copy()
        got = compiled.on_user(pose)
        # C's IK takes cos and sin where numpy takes acos: a near-straight arm (acos at +-1) turns 1e-16
        # into 1e-8 (tests/test_native.py's limb IK allows the same micrometre)
        np.testing.assert_allclose(got.positions, want_pos, rtol=0, atol=1e-6)
        np.testing.assert_allclose(got.rotations, want_rot, rtol=0, atol=1e-6)
        assert got.frame == pose.frame and got.contacts is pose.contacts


@needs_native
def test_sending_a_pose_on_the_users_body_makes_no_arrays(poses):
    """The compiled path is one ctypes call on buffers bound once: what a frame's memory peaks at is
    the call's own objects (numpy's was ~10 KB of temporaries a frame)."""
    import tracemalloc
    body = UserBody(1.06, 0.95)
    rows = [as_pose(r) for r in poses[:50]]
    pose = rows[0]
    for r in rows:                      # the same input arrays each frame, as the pipeline's output pose
        np.copyto(pose.positions, r.positions)
        np.copyto(pose.rotations, r.rotations)
        body.on_user(pose)
    tracemalloc.start()
    try:
        peaks = []
        for r in rows * 4:
            np.copyto(pose.positions, r.positions)
            np.copyto(pose.rotations, r.rotations)
            before = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            body.on_user(pose)
            peaks.append(tracemalloc.get_traced_memory()[1] - before)
    finally:
        tracemalloc.stop()
    assert max(peaks) < 1024, max(peaks)
    reference = UserBody(1.06, 0.95, compiled=False)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        reference.on_user(pose)
        numpy_peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    assert numpy_peak > 4 * max(peaks)        # the measure sees numpy's temporaries
