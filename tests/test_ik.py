"""Two-bone IK and foot-contact locks."""
import numpy as np

from edge import quat
from edge.ik import FootLock, apply_limb_ik, smoothstep
from edge.skeleton import JOINT, NUM_JOINTS, OFFSETS, PARENTS, fk

LEGS = np.array([[JOINT[f"{s}_hip"], JOINT[f"{s}_knee"], JOINT[f"{s}_ankle"]] for s in "lr"])
POLE = np.array([[0, 0, 1.0], [0, 0, 1.0]])


def random_poses(B, seed=0):
    rng = np.random.default_rng(seed)
    q = quat.normalize(np.tile([1.0, 0, 0, 0], (B, NUM_JOINTS, 1)) + 0.2 * rng.standard_normal((B, NUM_JOINTS, 4)))
    return quat.to_matrix(q)


def test_leg_ik_reaches_reachable_targets_and_keeps_bone_lengths():
    B = 200
    L = random_poses(B)
    W, P = fk(L, np.zeros((B, 3)))
    rng = np.random.default_rng(1)
    target = P[:, LEGS[:, 2]] + rng.normal(0, 0.1, (B, 2, 3))
    apply_limb_ik(L, W, P, PARENTS, LEGS, target, np.ones((B, 2)), POLE)
    W2, P2 = fk(L, np.zeros((B, 3)))
    reach = np.linalg.norm(target - P[:, LEGS[:, 0]], axis=-1) < 0.84
    assert reach.mean() > 0.2
    assert np.abs(np.linalg.norm(P2[:, LEGS[:, 2]] - target, axis=-1)[reach]).max() < 1e-9
    lengths = np.linalg.norm(P2[:, 1:] - P2[:, PARENTS[1:]], axis=-1)
    assert np.allclose(lengths, np.linalg.norm(OFFSETS[1:], axis=-1))
    # Unreachable targets: the leg points straight at them.
    far = ~reach
    d = P2[:, LEGS[:, 2]] - P2[:, LEGS[:, 0]]
    to = target - P2[:, LEGS[:, 0]]
    cos = np.sum(d * to, -1) / np.linalg.norm(d, axis=-1) / np.linalg.norm(to, axis=-1)
    assert cos[far].min() > 0.999


def test_ik_keeps_the_end_joint_world_orientation_and_zero_weight_changes_nothing():
    B = 20
    L = random_poses(B, 2)
    W, P = fk(L, np.zeros((B, 3)))
    L0 = L.copy()
    apply_limb_ik(L, W, P, PARENTS, LEGS, P[:, LEGS[:, 2]] + 0.3, np.zeros((B, 2)), POLE)
    assert np.allclose(L, L0, atol=1e-9)
    apply_limb_ik(L, W, P, PARENTS, LEGS, P[:, LEGS[:, 2]] + 0.05, np.ones((B, 2)), POLE)
    W2, _ = fk(L, np.zeros((B, 3)))
    assert np.allclose(W2[:, LEGS[:, 2]], W[:, LEGS[:, 2]], atol=1e-9)


def test_foot_lock_holds_then_releases_smoothly_over_ten_frames():
    lock = FootLock(samples=1, release_frames=10, max_slip=1.0)
    ankle = np.zeros((1, 2, 3))
    weights, targets = [], []
    for t in range(30):
        ankle[0, 0, 2] = 0.01 * t                      # the network's foot creeps forward
        contact = np.array([[1.0 if t < 10 else 0.0, 0.0]])
        tgt, w = lock.update(contact, ankle)
        weights.append(w[0, 0])
        targets.append(tgt[0, 0, 2])
    weights = np.array(weights)
    assert np.all(weights[:10] == 1) and np.allclose(targets[:10], 0)       # held where contact began
    release = weights[10:20]
    assert np.all(np.diff(release) < 0) and release[-1] == 0 and release[0] > 0.9
    assert np.allclose(release, 1 - smoothstep(np.arange(1, 11) / 10))
    assert np.all(weights[20:] == 0)


def test_foot_lock_lets_go_when_the_network_foot_slips_away():
    lock = FootLock(samples=1, max_slip=0.08)
    ankle = np.zeros((1, 2, 3))
    for t in range(20):
        ankle[0, 0, 2] = 0.02 * t
        _, w = lock.update(np.array([[1.0, 1.0]]), ankle)
    assert not lock.locked[0, 0] or np.linalg.norm(lock.lock_pos[0, 0] - ankle[0, 0]) <= 0.08
    assert lock.locked[0, 1]


def test_two_planted_feet_are_locked_at_least_the_lock_gap_apart():
    """A foot that plants closer than LOCK_GAP_M across the floor to the other, planted, foot is
    locked that far from it, along the line between them; the foot planted first stays; a foot that
    plants far enough away is locked where it is; two feet planting together move apart halfway each."""
    from edge.ik import FootLock
    from edge.physics import LOCK_GAP_M
    f = FootLock(1)
    ankles = np.array([[[0.04, 0.09, 0.0], [-0.50, 0.30, 0.0]]])
    f.update(np.array([[1.0, 0.0]]), ankles)               # left plants; right in the air
    ankles[0, 1] = [-0.04, 0.09, 0.0]
    lock, w = f.update(np.array([[1.0, 1.0]]), ankles)     # right plants 8 cm from the left
    np.testing.assert_allclose(lock[0, 0], [0.04, 0.09, 0.0])
    np.testing.assert_allclose(lock[0, 1], [0.04 - LOCK_GAP_M, 0.09, 0.0])
    g = FootLock(1)
    lock, _ = g.update(np.array([[1.0, 1.0]]), np.array([[[0.02, 0.09, 0.03], [-0.02, 0.09, 0.0]]]))
    d = lock[0, 1] - lock[0, 0]
    assert abs(np.hypot(d[0], d[2]) - LOCK_GAP_M) < 1e-12
    np.testing.assert_allclose(lock[0].mean(0), [0.0, 0.09, 0.015])      # halfway each
    h = FootLock(1)
    far = np.array([[[0.10, 0.09, 0.0], [-0.10, 0.09, 0.0]]])
    lock, _ = h.update(np.array([[1.0, 1.0]]), far)
    np.testing.assert_allclose(lock, far)


ARMS = np.array([[JOINT[f"{s}_shoulder"], JOINT[f"{s}_elbow"], JOINT[f"{s}_wrist"]] for s in "lr"])


def _elbow_side(P):
    """The elbow's unit direction off the shoulder-wrist line [B,2,3], and that line's direction."""
    sh, el, wr = P[:, ARMS[:, 0]], P[:, ARMS[:, 1]], P[:, ARMS[:, 2]]
    n = (wr - sh) / np.linalg.norm(wr - sh, axis=-1, keepdims=True)
    u = (el - sh) - np.sum((el - sh) * n, -1, keepdims=True) * n
    return u / np.linalg.norm(u, axis=-1, keepdims=True), n


def test_swivel_puts_the_elbow_opposite_where_the_hand_points_and_keeps_wrist_and_hand():
    from edge.ik import swivel_to_hands
    B = 200
    L = random_poses(B, 3)
    W, P = fk(L, np.zeros((B, 3)))
    _, n = _elbow_side(P)
    h = np.random.default_rng(4).standard_normal((B, 2, 3))
    h_across = h - np.sum(h * n, -1, keepdims=True) * n
    h_across /= np.linalg.norm(h_across, axis=-1, keepdims=True)
    # Hands whose long axis (the forearm's rest direction, OFFSETS[wrist]) points along h_across.
    axis = OFFSETS[ARMS[:, 2]] / np.linalg.norm(OFFSETS[ARMS[:, 2]], axis=-1, keepdims=True)
    W[:, ARMS[:, 2]] = quat.to_matrix(quat.between(np.broadcast_to(axis, (B, 2, 3)), h_across))
    L[:, ARMS[:, 2]] = np.swapaxes(W[:, ARMS[:, 1]], -1, -2) @ W[:, ARMS[:, 2]]
    hands, wrists = W[:, ARMS[:, 2]].copy(), P[:, ARMS[:, 2]].copy()
    swivel_to_hands(L, W, P, PARENTS, ARMS, OFFSETS, gain=50.0, clearance=0.0)
    side, _ = _elbow_side(P)
    assert np.sum(side * h_across, -1).max() < -0.99        # the far side from the hand
    assert np.allclose(P[:, ARMS[:, 2]], wrists, atol=1e-9) and np.allclose(W[:, ARMS[:, 2]], hands, atol=1e-9)
    W2, P2 = fk(L, np.zeros((B, 3)))                        # local, world and positions still agree
    assert np.allclose(P2, P, atol=1e-9) and np.allclose(W2, W, atol=1e-9)


def test_swivel_turns_an_elbow_out_of_the_torso_and_leaves_clear_ones_alone():
    from edge.ik import ELBOW_CLEARANCE_M, TORSO_LINE, closest_on_polyline, swivel_to_hands
    B = 400
    L = random_poses(B, 5)
    shoulders = quat.normalize(np.random.default_rng(6).standard_normal((B, 2, 4)))
    L[:, ARMS[:, 0]] = quat.to_matrix(shoulders)              # arms anywhere, many elbows in the chest
    W, P = fk(L, np.zeros((B, 3)))

    def torso_distance(P):
        el = P[:, ARMS[:, 1]]
        return np.linalg.norm(el - closest_on_polyline(el, P[:, TORSO_LINE]), axis=-1)

    def farthest_on_circle(P):          # the swivel circle's farthest point from the torso line, sampled
        sh, el = P[:, ARMS[:, 0]], P[:, ARMS[:, 1]]
        u, n = _elbow_side(P)
        along = np.sum((el - sh) * n, -1, keepdims=True)
        r = np.linalg.norm((el - sh) - along * n, axis=-1, keepdims=True)
        v = np.cross(n, u)
        far = np.zeros(P.shape[0:1] + (2,))
        for a in np.linspace(0.0, 2 * np.pi, 180, endpoint=False):
            e = sh + along * n + r * (np.cos(a) * u + np.sin(a) * v)
            far = np.maximum(far, np.linalg.norm(e - closest_on_polyline(e, P[:, TORSO_LINE]), axis=-1))
        return far

    before, room = torso_distance(P), farthest_on_circle(P)
    swivel_to_hands(L, W, P, PARENTS, ARMS, OFFSETS, gain=0.0)
    after = torso_distance(P)
    inside = before < 0.10
    assert inside.sum() > 20
    # Where the circle has room (15 cm), the elbow gets out, even with the hand reaching across the
    # chest, where the elbow's own way out runs along the arm (the guard follows the circle's centre).
    roomy = inside & (room > 0.15)
    assert roomy.sum() > 10 and after[roomy].min() > 0.095
    # A single proportional push, not a search: never deeper, mostly well out (where the swivel circle
    # allows: a wrist near the chest keeps its elbow near too).
    assert (after[inside] >= before[inside] - 1e-9).all()
    assert np.median(after[inside] - before[inside]) > 0.02
    assert (after[inside] >= 0.10).mean() > 0.4
    clear = before > ELBOW_CLEARANCE_M + 0.01
    assert np.allclose(after[clear], before[clear], atol=1e-9)


ARM_LENGTH = np.linalg.norm(OFFSETS[ARMS[:, 1]], axis=-1) + np.linalg.norm(OFFSETS[ARMS[:, 2]], axis=-1)
COLLARS = PARENTS[ARMS[:, 0]]


def _consistent(L, W, P):
    """Local, world and positions still describe one pose."""
    W2, P2 = fk(L, np.zeros((L.shape[0], 3)))
    return np.allclose(P2, P, atol=1e-9) and np.allclose(W2, W, atol=1e-9)


def test_a_controller_beyond_reach_draws_the_shoulder_toward_it_and_the_wrist_onto_it():
    """Shoulders that follow the reach (edge.ik.shoulders_to_reach): a controller farther from the
    shoulder than REACH_START of the arm swings the collar toward it by the excess (at most
    SHOULDER_REACH_MAX_M), so the arm IK reaches it; nearer ones leave the pose exactly as it was."""
    from edge.ik import REACH_START, SHOULDER_REACH_MAX_M, shoulders_to_reach
    B = 400
    L = random_poses(B, 7)
    W, P = fk(L, np.zeros((B, 3)))
    rng = np.random.default_rng(8)
    way = rng.standard_normal((B, 2, 3))
    way /= np.linalg.norm(way, axis=-1, keepdims=True)
    reach = rng.uniform(0.6, 1.12, (B, 2))                  # the controller's distance over the arm's length
    targets = P[:, ARMS[:, 0]] + (reach * ARM_LENGTH)[..., None] * way
    before = [x.copy() for x in (L, W, P)]
    shoulders_to_reach(L, W, P, PARENTS, ARMS, OFFSETS, targets)
    assert _consistent(L, W, P)
    moved = np.linalg.norm(P[:, ARMS[:, 0]] - before[2][:, ARMS[:, 0]], axis=-1)
    near = reach < REACH_START - 1e-6
    both_near = near.all(-1)
    assert both_near.sum() > 50 and np.allclose(P[both_near], before[2][both_near], rtol=0, atol=1e-12)
    assert np.allclose(L[both_near], before[0][both_near], rtol=0, atol=1e-12)
    far = ~near
    assert far.sum() > 100 and (moved[far] > 0).all() and moved.max() <= SHOULDER_REACH_MAX_M + 1e-9
    gap_before = np.linalg.norm(targets - before[2][:, ARMS[:, 0]], axis=-1)
    gap_after = np.linalg.norm(targets - P[:, ARMS[:, 0]], axis=-1)
    closer = gap_before[far] - gap_after[far]                               # toward the controller
    assert (closer > -1e-9).all() and closer.mean() > 0.5 * moved[far].mean()
    collar_bone = P[:, ARMS[:, 0]] - P[:, COLLARS]
    assert np.allclose(np.linalg.norm(collar_bone, axis=-1), np.linalg.norm(OFFSETS[ARMS[:, 0]], axis=-1))

    def wrist_miss(L, W, P):
        L, W, P = L.copy(), W.copy(), P.copy()
        apply_limb_ik(L, W, P, PARENTS, ARMS, targets, np.ones((B, 2)), POLE, None, OFFSETS)
        return np.linalg.norm(P[:, ARMS[:, 2]] - targets, axis=-1)
    miss_then, miss_now = wrist_miss(*before), wrist_miss(L, W, P)
    beyond = reach > 1.0
    assert beyond.sum() > 30 and miss_now[beyond].mean() < 0.6 * miss_then[beyond].mean()
    assert miss_now[reach < 1.0].max() < 1e-6 and (miss_now <= miss_then + 1e-9).all()


def test_a_straight_arm_whose_elbow_is_in_the_torso_moves_its_shoulder_out():
    """A straight arm has no swivel circle: where its elbow is still nearer than ELBOW_MIN_M to the
    torso's line, the collar moves the shoulder out across the arm (edge.ik.shoulders_out_of_torso) and
    the arm is re-aimed at the wrist, the hand's rotation kept; clear elbows are left exactly alone."""
    from edge.ik import ELBOW_MIN_M, SHOULDER_PUSH_MAX_M, TORSO_LINE, closest_on_polyline, shoulders_out_of_torso
    B = 600
    L = random_poses(B, 9)
    L[:, ARMS[:, 0]] = quat.to_matrix(quat.normalize(np.random.default_rng(10).standard_normal((B, 2, 4))))
    L[:, ARMS[:, 1]] = np.eye(3)                               # straight arms, pointing anywhere
    W, P = fk(L, np.zeros((B, 3)))

    def torso_distance(P):
        el = P[:, ARMS[:, 1]]
        return np.linalg.norm(el - closest_on_polyline(el, P[:, TORSO_LINE]), axis=-1)
    before, wrists, hands = torso_distance(P), P[:, ARMS[:, 2]].copy(), W[:, ARMS[:, 2]].copy()
    P0 = P.copy()
    shoulders_out_of_torso(L, W, P, PARENTS, ARMS)
    after = torso_distance(P)
    assert _consistent(L, W, P)
    push = np.linalg.norm(P[:, ARMS[:, 0]] - P0[:, ARMS[:, 0]], axis=-1)
    inside = before < ELBOW_MIN_M
    assert inside.sum() > 20
    # One first-order step, not a search: out, bar a fraction of a millimetre where a long push curves.
    assert (after[inside] > before[inside] - 1e-3).all() and push.max() <= SHOULDER_PUSH_MAX_M + 1e-9
    assert (after[inside] >= ELBOW_MIN_M - 1e-3).mean() > 0.2          # out, where 4 cm of collar can take it
    assert np.median(after[inside] - before[inside]) > 0.01
    # The wrist keeps the hand's rotation and moves only by the step's curvature: the shoulder's arc about
    # the collar joint and the arm's about the wrist (push^2 over twice the collar, and over twice the arm).
    wrist_moved = np.linalg.norm(P[:, ARMS[:, 2]] - wrists, axis=-1)
    collar = np.linalg.norm(OFFSETS[ARMS[:, 0]], axis=-1)
    assert (wrist_moved <= push ** 2 * (0.5 / collar + 0.5 / ARM_LENGTH) + 1e-9).all()
    assert np.allclose(W[:, ARMS[:, 2]], hands, atol=1e-12)
    clear = ~inside.any(-1)
    assert np.allclose(P[clear], P0[clear], rtol=0, atol=1e-12)
