"""Physical plausibility: the geometry and metrics (edge.physics, motion.metrics), the floor clamp in the
foot IK, and the selection criterion (numpy and compiled core alike)."""
import numpy as np
import pytest

from motion import metrics
from edge.criteria import FrameContext, PhysicalPlausibility
from edge.physics import FLOOR_ANKLE, FLOOR_TOE, foot_height, leg_gap, segment_distance
from edge.options import PipelineOptions
from edge.frame import supported_contacts
from edge.pipeline import Pipeline
from edge.skeleton import ANKLES, JOINT, REST, TOES, PELVIS_HEIGHT
from motion.takes import from_sample
from conftest import SAMPLE

STANDING = REST + [0.0, PELVIS_HEIGHT, 0.0]          # the rest pose on the floor


def test_segment_distance_matches_a_dense_search():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(150, 4, 3))        # 150 pairs x 401 x 401 points: 0.6 GB of differences, 5 s
    d = segment_distance(P[:, 0], P[:, 1], P[:, 2], P[:, 3])
    s = np.linspace(0, 1, 401)[None, :, None]
    a, b = P[:, :1] + (P[:, 1:2] - P[:, :1]) * s, P[:, 2:3] + (P[:, 3:4] - P[:, 2:3]) * s
    dense = np.linalg.norm(a[:, :, None] - b[:, None], axis=-1).min((1, 2))
    assert np.all(d <= dense + 1e-12) and np.all(dense - d < 2e-3)


def test_metrics_see_a_sunk_foot_crossed_legs_and_a_floating_contact():
    pose = np.repeat(STANDING[None], 4, 0)
    assert np.allclose(foot_height(pose[0]), 0.0) and leg_gap(pose[0]) == pytest.approx(0.18)
    pose[1, [JOINT["l_ankle"], JOINT["l_toe"]], 1] -= 0.05            # sinks 3 cm past the 2 cm tolerance
    pose[2, [JOINT["l_knee"], JOINT["l_ankle"], JOINT["l_toe"]], 0] = -0.05     # left shin across the right
    pose[3, [JOINT["r_ankle"], JOINT["r_toe"]], 1] += 0.2             # lifted 20 cm ...
    contacts = np.array([[1, 1], [1, 1], [1, 1], [1, 1.0]])           # ... while said to be in contact
    m = metrics.summarize_physical([metrics.physical_metrics(pose, contacts)])
    assert m["penetration_rate"] == 0.25 and m["penetration_cm"] == pytest.approx(3.0)
    assert m["leg_intersect_rate"] == 0.25 and m["float_rate"] == 0.25 and m["physical_sum"] == 0.75


def test_foot_ik_never_leaves_a_foot_in_the_floor_on_either_path():
    """Lower the whole take 15 cm: the decoder's feet go into the floor, and the leg IK lifts them out."""
    take = from_sample(SAMPLE)
    sig = take.signals
    sunk = type(sig)(**{**vars(sig), "head_pos": sig.head_pos - [0, 0.15, 0], "hand_pos": sig.hand_pos - [0, 0.15, 0]})
    for native in (True, False):
        pipe = Pipeline(PipelineOptions(samples=1, use_native=native))
        low, lifted = [], []
        for t in range(300):
            pose = pipe.step(sunk.slice(t, t + 1))
            low.append(min(pose.positions[ANKLES, 1].min() - FLOOR_ANKLE, pose.positions[TOES, 1].min() - FLOOR_TOE))
            lifted.append(pipe.bufs.floor_lift[0].max())
        assert min(low) > -1e-6, f"native={native}: a foot {-min(low) * 100:.1f} cm under the floor"
        assert max(lifted) > 0.02                 # the clamp did work: the raw feet were under


def test_physical_criterion_prefers_the_clean_sample_and_the_core_agrees_with_numpy():
    rng = np.random.default_rng(2)
    pos = np.repeat(STANDING[None], 40, 0) + rng.normal(0, 0.01, (40, 21, 3))
    pos[5, [JOINT["l_knee"], JOINT["l_ankle"], JOINT["l_toe"]], 0] = -0.05      # crossed legs
    pos[6, [JOINT["r_ankle"], JOINT["r_toe"]], 1] += 0.3                        # a floating contact
    lift = np.zeros((40, 2))
    lift[7] = 0.04                                                              # feet lifted out of the floor
    contacts = np.ones((40, 2), np.float32)
    ctx = FrameContext(0, np.ascontiguousarray(pos), None, None, contacts=contacts, floor_lift=lift)
    fast = PhysicalPlausibility().cost(ctx).copy()
    slow = PhysicalPlausibility(use_native=False).cost(ctx)
    assert np.allclose(fast, slow, atol=1e-12)
    assert fast[5] > 0.05 and fast[6] > 0.2 and fast[7] == pytest.approx(0.08)
    clean = np.delete(fast, [5, 6, 7])
    assert clean.max() < 0.01


def test_a_wider_clearance_charges_legs_that_come_close_before_they_cross_on_both_paths():
    """selection.physical.clearance: legs 12 cm apart cost nothing at the metric's 10 cm and 1 cm at 13 cm
    (the switch can start before they cross), in the compiled core and in numpy alike."""
    pos = np.repeat(STANDING[None], 2, 0)
    pos[1, [JOINT["l_hip"], JOINT["l_knee"], JOINT["l_ankle"], JOINT["l_toe"]], 0] -= 0.06    # 18 -> 12 cm
    assert leg_gap(pos[1]) == pytest.approx(0.12)
    ctx = FrameContext(0, np.ascontiguousarray(pos), None, None, contacts=np.zeros((2, 2), np.float32),
                       floor_lift=np.zeros((2, 2)))
    for native in (True, False):
        assert np.allclose(PhysicalPlausibility(use_native=native).cost(ctx), 0.0)
        wide = PhysicalPlausibility(use_native=native, clearance=0.13).cost(ctx)
        assert wide[0] == 0.0 and wide[1] == pytest.approx(0.01), f"native={native}"


def test_a_foot_in_the_air_is_not_reported_in_contact_whatever_the_decoder_says():
    pose = STANDING.copy()
    assert np.allclose(supported_contacts(np.array([1.0, 0.8]), pose), [1.0, 0.8])      # both on the floor
    pose[[JOINT["r_ankle"], JOINT["r_toe"]], 1] += 0.055                                # right foot 5.5 cm up
    assert np.allclose(supported_contacts(np.array([1.0, 1.0]), pose), [1.0, 0.5])      # fading
    pose[[JOINT["r_ankle"], JOINT["r_toe"]], 1] += 0.1
    assert np.allclose(supported_contacts(np.array([1.0, 1.0]), pose), [1.0, 0.0])      # in the air


@pytest.mark.parametrize("native", [True, False])
def test_the_output_never_says_contact_for_a_foot_in_the_air(native):
    """A foot's reported contact is at most what its height lets it bear (edge.physics.support)."""
    from edge.physics import support
    take = from_sample(SAMPLE)
    pipe = Pipeline(PipelineOptions(samples=4, use_native=native))
    lifted = 0
    for t in range(400):
        pose = pipe.step(take.signals.slice(t, t + 1))
        if pose is None:
            continue
        bearable = support(foot_height(pose.positions))
        lifted += int((bearable < 1).sum())
        assert np.all(pose.contacts <= bearable + 1e-12)
    assert lifted > 50                      # a walk lifts its feet: the check saw some


def crossing_pose(inward):
    """STANDING with the right leg swung `inward` (rad) across the body about the forward axis, and
    5 cm forward, as a swing foot passes the planted one."""
    from edge.quat import from_axis_angle, rotate
    pose = STANDING.copy()
    hip = pose[JOINT["r_hip"]]
    q = from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array(inward))
    for j in ("r_knee", "r_ankle", "r_toe"):
        pose[JOINT[j]] = hip + rotate(q, pose[JOINT[j]] - hip) + [0.0, 0.0, 0.05]
    return pose


def test_the_leg_guard_moves_a_free_foot_away_from_the_planted_leg_and_leaves_planted_feet():
    """guard_legs: the right (free) foot's goal moves away from the left (planted) leg across the floor
    by the shortfall over how much of an ankle's move reaches the closest point; the planted foot's goal
    stays; two planted feet, legs far enough apart, or the guard at 0 move nothing."""
    from edge.ik import guard_legs
    from edge.physics import LEG_GUARD_M, LEG_GUARD_MAX_PUSH_M, leg_pair_distances
    pose = crossing_pose(0.12)[None]
    gap = leg_gap(pose)[0]
    assert gap < LEG_GUARD_M - 0.03
    goal = pose[:, ANKLES].copy()
    guard_legs(pose, goal, np.array([[1.0, 0.0]]))
    np.testing.assert_array_equal(goal[0, 0], pose[0, ANKLES[0]])
    moved = goal[0, 1] - pose[0, ANKLES[1]]
    assert moved[1] == 0.0 and moved[0] < -0.02            # across the floor, to the body's right (-x)
    # At least the shortfall (the hip stays put, so the ankle must move further), at most the cap.
    assert LEG_GUARD_M - gap - 1e-12 <= np.linalg.norm(moved) <= LEG_GUARD_MAX_PUSH_M + 1e-12
    shin_shin = leg_pair_distances(pose)[0].argmin() == 3
    assert shin_shin
    for weights, clearance in (([1.0, 1.0], LEG_GUARD_M), ([0.0, 0.0], gap - 0.01), ([0.0, 1.0], 0.0)):
        same = pose[:, ANKLES].copy()
        guard_legs(pose, same, np.array([weights]), clearance)
        np.testing.assert_array_equal(same, pose[:, ANKLES])


def test_the_foot_ik_swings_a_free_leg_around_the_other_on_both_paths():
    """On the bundled walk (a narrow gait the model makes narrower, its shins passing within 10 cm),
    the leg guard leaves a fraction of the crossing frames, on the compiled and the numpy path alike,
    without moving the rest of the body."""
    from edge.physics import INTERSECT_M
    take = from_sample(SAMPLE)
    T = 600
    crossing, guarded = {}, {}
    for native in (True, False):
        for guard in (0.0, None):
            opts = PipelineOptions(samples=1, use_native=native)
            pipe = Pipeline(opts if guard is None else PipelineOptions(samples=1, use_native=native, leg_guard=guard))
            pos = np.array([pipe.step(take.signals.slice(t, t + 1)).positions.copy() for t in range(T)])
            crossing[native, guard] = int((leg_gap(pos[60:]) < INTERSECT_M).sum())
            if guard is None:
                guarded[native] = pos
            else:
                unguarded = pos
        upper = [JOINT[j] for j in ("pelvis", "spine", "chest", "neck", "head", "l_wrist", "r_wrist")]
        assert np.abs(guarded[native][:, upper] - unguarded[:, upper]).max() < 1e-9
    assert crossing[True, 0.0] >= 10, crossing          # v0.4: 35 frames; v0.4.1 keeps the legs wider: 13
    assert crossing[True, None] <= crossing[True, 0.0] / 4, crossing
    np.testing.assert_allclose(guarded[True], guarded[False], rtol=0, atol=1e-9)
