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
