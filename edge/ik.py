"""Analytic two-bone IK and foot-contact locking, batched over samples and limbs (numpy).

SSI 3.1: when a foot is in contact, lock it and solve the thigh/shin analytically; LoBSTR 3.4.1: on
release, ease from the locked position back to the network's foot over 10 frames (slow-in/slow-out).
The arm pass puts the wrists on the controllers (the SSI paper's section 6 limitation): a controller
beyond reach draws the shoulder toward it first (shoulders_to_reach), the elbow turns about the
shoulder-wrist line toward the hand's side and out of the torso (swivel_to_hands), and a straight arm
still in the torso has its shoulder moved out (shoulders_out_of_torso). guard_legs
moves free feet's goals so the leg IK swings a leg around the other instead of through it.
"""
import numpy as np

from edge.physics import (LEG_GUARD_M, LEG_GUARD_MAX_PUSH_M, LEG_SEGMENTS, LOCK_GAP_M, LOCK_SNAP_M, lowest_point,
                          segment_closest, support)

from edge.quat import cross


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def _normalize(v, eps=1e-9):
    return v / np.maximum(np.sqrt(_dot(v, v))[..., None], eps)


def _axis_angle_matrix(axis, angle):
    """Rodrigues: rotation matrices [...,3,3] about unit axes [...,3] by angles [...]: I + s K + (1-c) K^2."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    outer = axis[..., :, None] * axis[..., None, :] * (1.0 - c)[..., None, None]
    sx, sy, sz = s * x, s * y, s * z
    outer[..., 0, 0] += c
    outer[..., 1, 1] += c
    outer[..., 2, 2] += c
    outer[..., 0, 1] -= sz
    outer[..., 1, 0] += sz
    outer[..., 0, 2] += sy
    outer[..., 2, 0] -= sy
    outer[..., 1, 2] -= sx
    outer[..., 2, 1] += sx
    return outer


def _angle_between(u, v):
    return np.arccos(np.clip(_dot(u, v) / np.sqrt(_dot(u, u) * _dot(v, v) + 1e-18), -1.0, 1.0))


def two_bone_ik(a, b, c, target, a_rot, b_rot, pole):
    """Rotate a chain a->b->c (e.g. hip->knee->ankle) so c reaches `target`, keeping bone lengths.

    a, b, c, target, pole [...,3]; a_rot, b_rot world rotations [...,3,3].
    Returns the new world rotations of a and b. `pole` is the bend direction used when the chain is straight.
    """
    ab, cb, ca, ta = b - a, c - b, c - a, target - a
    lab = np.sqrt(_dot(ab, ab))
    lcb = np.sqrt(_dot(cb, cb))
    lat = np.clip(np.sqrt(_dot(ta, ta)), 1e-4, (lab + lcb) * (1 - 1e-4))
    ac_ab_0 = _angle_between(ca, ab)
    ba_bc_0 = _angle_between(-ab, cb)
    ac_at_0 = _angle_between(ca, ta)
    ac_ab_1 = np.arccos(np.clip((lcb * lcb - lab * lab - lat * lat) / (-2 * lab * lat), -1, 1))
    ba_bc_1 = np.arccos(np.clip((lat * lat - lab * lab - lcb * lcb) / (-2 * lab * lcb), -1, 1))
    bend = cross(ca, ab)
    straight = _dot(bend, bend)[..., None] < 1e-12
    axis0 = _normalize(np.where(straight, cross(ca, pole), bend))
    axis1 = _normalize(cross(ca, ta))
    r0 = _axis_angle_matrix(axis0, ac_ab_1 - ac_ab_0)
    r1 = _axis_angle_matrix(axis0, ba_bc_1 - ba_bc_0)
    r20 = _axis_angle_matrix(axis1, ac_at_0) @ r0
    return r20 @ a_rot, r20 @ (r1 @ b_rot)


def apply_limb_ik(local_rot, world_rot, world_pos, parents, chains, targets, weights, poles, end_world_rot=None,
                  offsets=None):
    """Solve several two-bone chains for a batch of poses, updating the pose in place.

    local_rot, world_rot [B,J,3,3], world_pos [B,J,3]; chains [K,3] joint indices (root, mid, end);
    targets [B,K,3]; weights [B,K] in [0,1] blend from the current end position to the target;
    poles [K,3] bend directions in the mid joint's frame; end_world_rot [B,K,3,3] sets the end joints'
    world orientation (None keeps it). With `offsets` (the skeleton's), world rotations and positions
    of the chain joints are updated too; positions of joints below the chain ends are not.
    """
    ia, ib, ic = chains[:, 0], chains[:, 1], chains[:, 2]
    a, b, c = world_pos[:, ia], world_pos[:, ib], world_pos[:, ic]
    goal = c + weights[..., None] * (targets - c)
    a_rot, b_rot = world_rot[:, ia], world_rot[:, ib]
    pole = (b_rot @ poles[..., None])[..., 0]
    a_new, b_new = two_bone_ik(a, b, c, goal, a_rot, b_rot, pole)
    end_rot = world_rot[:, ic] if end_world_rot is None else end_world_rot
    parent_rot = world_rot[:, parents[ia]]
    local_rot[:, ia] = np.swapaxes(parent_rot, -1, -2) @ a_new
    local_rot[:, ib] = np.swapaxes(a_new, -1, -2) @ b_new
    local_rot[:, ic] = np.swapaxes(b_new, -1, -2) @ end_rot
    if offsets is not None:
        world_rot[:, ia], world_rot[:, ib], world_rot[:, ic] = a_new, b_new, end_rot
        knee = a + (a_new @ offsets[ib][..., None])[..., 0]
        world_pos[:, ib] = knee
        world_pos[:, ic] = knee + (b_new @ offsets[ic][..., None])[..., 0]


# How strongly a controller's hand axis turns the elbow about the shoulder-wrist line, against the
# decoder's own elbow (edge.ik.swivel_to_hands). Chosen on val's unseen people with their real hand
# orientations and with a wrist bend added (bench/upper_body.py --bend): elbows 4.89/4.12 cm at 2,
# 4.81/4.02 at 2.25, 4.74/3.94 at 2.5 with val's hands; 6.24/5.66, 6.29/5.71, 6.34/5.78 with the hands
# bent (a human p50 bend of 18 deg). 2.25 is the least gain that brings the elbows under 4.5 cm with the
# hands as recorded and costs 0.05 cm with them bent; gain 1 is never worse than none.
ELBOW_FROM_HAND = 2.25
# The torso as a line through pelvis, spine, chest and neck; an elbow nearer to it than
# ELBOW_CLEARANCE_M is inside a slim torso (bench/upper_body.py counts those at 0.10 m), and the swivel
# turns it out, GUARD_GAIN times the shortfall's share of the clearance.
TORSO_LINE = np.array([0, 1, 2, 3])
ELBOW_CLEARANCE_M = 0.13
GUARD_GAIN = 3.0
# A straight arm has no circle to turn its elbow on. Where its elbow is still nearer than ELBOW_MIN_M to
# the torso's line, the collar moves the shoulder out, as a shoulder girdle does (at most
# SHOULDER_PUSH_MAX_M), and the arm is re-aimed at the wrist (edge.ik.shoulders_out_of_torso). The
# truth of val's unseen people has no elbow nearer than 11 cm (bench/upper_body.py counts 10 cm as inside).
ELBOW_MIN_M = 0.11
SHOULDER_PUSH_MAX_M = 0.04
# The controllers as evidence for the shoulders: where a controller is farther from the decoder's
# shoulder than REACH_START of the arm's length, the collar swings the shoulder toward it by the excess
# (at most SHOULDER_REACH_MAX_M), as a shoulder girdle follows a far reach (edge.ik.shoulders_to_reach).
REACH_START = 0.97
SHOULDER_REACH_MAX_M = 0.06


def closest_on_polyline(p, line):
    """The closest points on polylines line [B,L,3] to points p [B,K,3] -> [B,K,3]."""
    a, d = line[:, None, :-1], (line[:, 1:] - line[:, :-1])[:, None]            # [B,1,L-1,3]
    t = np.clip(_dot(p[:, :, None] - a, d) / np.maximum(_dot(d, d), 1e-12), 0.0, 1.0)
    q = a + t[..., None] * d                                                      # [B,K,L-1,3]
    nearest = _dot(p[:, :, None] - q, p[:, :, None] - q).argmin(-1)
    return np.take_along_axis(q, nearest[..., None, None], axis=2)[:, :, 0]


def swivel_to_hands(local, world, pos, parents, arms, offsets, gain=ELBOW_FROM_HAND, torso=TORSO_LINE,
                    clearance=ELBOW_CLEARANCE_M):
    """Turn each arm about its shoulder-wrist line so the forearm runs nearer the hand's long axis, and
    the elbow stays out of the torso.

    With the wrist straight the forearm runs along the hand; a wrist bends only so far (flexion and
    deviation), so where the controller points says on which side of the shoulder-wrist line the
    elbow is. The elbow's direction off that line becomes the decoder's own minus `gain` times the
    hand axis's part across the line (the far side from where the hand points), renormalised. Where
    that puts the elbow closer than `clearance` to the torso's line (the joints `torso`), the direction
    is pushed away from it in proportion. The wrist stays where it is and keeps the hand's rotation.
    arms [K,3] (shoulder, elbow, wrist) chains already solved onto the controllers (world[:, wrist] is
    the hand's rotation); local, world [B,J,3,3] and pos [B,J,3] are updated in place."""
    ia, ib, ic = arms[:, 0], arms[:, 1], arms[:, 2]
    sh, el, wr = pos[:, ia], pos[:, ib], pos[:, ic]
    n = _normalize(wr - sh)
    e = el - sh
    along = _dot(e, n)
    u = e - along[..., None] * n
    axis = offsets[ic] / np.linalg.norm(offsets[ic], axis=-1, keepdims=True)
    h = (world[:, ic] @ axis[..., None])[..., 0]
    u_len = np.sqrt(_dot(u, u))
    u = u / np.maximum(u_len, 1e-9)[..., None]
    t = _normalize(u - gain * (h - _dot(h, n)[..., None] * n))
    centre = sh + along[..., None] * n                                           # of the elbow's circle
    elbow = centre + u_len[..., None] * t                                        # where t puts the elbow
    gap = elbow - closest_on_polyline(elbow, pos[:, torso])
    dist = np.sqrt(_dot(gap, gap))
    # Out along the circle's own way from the torso (its centre's, across the arm): the elbow's own
    # way out can run along the arm when the hand reaches across the chest, and turning gains nothing.
    away = centre - closest_on_polyline(centre, pos[:, torso])
    away -= _dot(away, n)[..., None] * n
    push = GUARD_GAIN * np.maximum(clearance - dist, 0.0) / max(clearance, 1e-9)   # clearance 0: no guard
    t = t + push[..., None] * _normalize(away)
    t_len = np.sqrt(_dot(t, t))
    t = t / np.maximum(t_len, 1e-9)[..., None]
    keep = (u_len < 1e-6) | (t_len < 1e-6)          # a straight arm, or no side to prefer
    c = np.where(keep, 1.0, np.clip(_dot(u, t), -1.0, 1.0))
    s = np.where(keep, 0.0, _dot(cross(u, t), n))
    turn = _axis_angle_matrix(n, np.arctan2(s, c))
    a_new, b_new = turn @ world[:, ia], turn @ world[:, ib]
    pos[:, ib] = sh + (turn @ e[..., None])[..., 0]
    local[:, ia] = np.swapaxes(world[:, parents[ia]], -1, -2) @ a_new
    local[:, ib] = np.swapaxes(a_new, -1, -2) @ b_new
    local[:, ic] = np.swapaxes(b_new, -1, -2) @ world[:, ic]
    world[:, ia], world[:, ib] = a_new, b_new


def _swing_matrix(a, b):
    """Shortest-arc rotation matrices [...,3,3] taking directions a [...,3] to b (identity where they agree)."""
    axis = cross(a, b)
    return _axis_angle_matrix(_normalize(axis), np.arctan2(np.sqrt(_dot(axis, axis)), _dot(a, b)))


def shoulders_to_reach(local, world, pos, parents, arms, offsets, targets, start=REACH_START,
                       max_move=SHOULDER_REACH_MAX_M):
    """Before the arm IK: where a wrist's target is farther from the shoulder than `start` of the arm's
    length, swing the collar so the shoulder moves toward it by the excess (at most `max_move`), the part
    of that move across the collar bone (its length is kept); the arm comes along as it is, for the IK
    to solve. arms [K,3] (shoulder, elbow, wrist); targets [B,K,3]; local, world
    [B,J,3,3] and pos [B,J,3] updated in place."""
    ia, ib, ic = arms[:, 0], arms[:, 1], arms[:, 2]
    ip = parents[ia]                                            # the collars
    co, sh = pos[:, ip], pos[:, ia]
    length = np.linalg.norm(offsets[ib], axis=-1) + np.linalg.norm(offsets[ic], axis=-1)
    to = targets - sh
    d = np.sqrt(_dot(to, to))
    move = np.clip(d - start * length, 0.0, max_move)
    bone = sh - co
    bone_len = np.sqrt(_dot(bone, bone))
    b = bone / np.maximum(bone_len, 1e-9)[..., None]
    way = to / np.maximum(d, 1e-9)[..., None]
    across = way - _dot(way, b)[..., None] * b                  # the collar moves the shoulder across its bone
    new_bone = _normalize(bone + move[..., None] * across) * bone_len[..., None]
    turn = _swing_matrix(bone, new_bone)
    sh_new = co + new_bone
    for j in (ib, ic):
        pos[:, j] = sh_new + (turn @ (pos[:, j] - sh)[..., None])[..., 0]
    pos[:, ia] = sh_new
    for j in (ip, ia, ib, ic):
        world[:, j] = turn @ world[:, j]
    local[:, ip] = np.swapaxes(world[:, parents[ip]], -1, -2) @ world[:, ip]


def shoulders_out_of_torso(local, world, pos, parents, arms, torso=TORSO_LINE, min_gap=ELBOW_MIN_M,
                           max_push=SHOULDER_PUSH_MAX_M):
    """Where an elbow is still nearer than `min_gap` to the torso's line after swivel_to_hands (a straight
    arm, whose elbow no turn moves), swing its collar so the shoulder steps across the arm and the collar
    bone, to the elbow's side away from the torso, as far as the elbow needs (at most `max_push`), and
    re-aim the arm at the wrist: turning about the wrist moves the elbow |wrist-elbow|/|wrist-shoulder|
    of what the shoulder moves. The wrist keeps the hand's rotation and moves only by the step's
    curvature (the push squared over twice the collar and over twice the arm: at most 7 mm at 4 cm).
    arms [K,3] (shoulder, elbow, wrist); local, world [B,J,3,3] and pos [B,J,3] updated in place."""
    ia, ib, ic = arms[:, 0], arms[:, 1], arms[:, 2]
    ip = parents[ia]                                            # the collars
    co, sh, el, wr = pos[:, ip], pos[:, ia], pos[:, ib], pos[:, ic]
    gap = el - closest_on_polyline(el, pos[:, torso])
    short = np.maximum(min_gap - np.sqrt(_dot(gap, gap)), 0.0)
    n = _normalize(wr - sh)
    bone = sh - co
    bone_len = np.sqrt(_dot(bone, bone))
    # The shoulder steps across both its collar bone (whose length is kept) and the arm (so the wrist
    # stays), to the side the elbow is out of the torso; re-aimed at the wrist, the elbow moves `lever`
    # of the step.
    step = _normalize(cross(bone, n))
    out = _dot(step, gap)
    step *= np.sign(out)[..., None]
    lever = np.sqrt(_dot(wr - el, wr - el)) / np.maximum(np.sqrt(_dot(wr - sh, wr - sh)), 1e-9)
    gain = lever * np.abs(out) / np.maximum(np.sqrt(_dot(gap, gap)), 1e-9)
    move = np.minimum(short / np.maximum(gain, 1e-3), max_push)
    new_bone = _normalize(bone + move[..., None] * step) * bone_len[..., None]
    collar_turn = _swing_matrix(bone, new_bone)
    sh_new = co + new_bone
    arm = collar_turn @ (wr - sh)[..., None]
    arm_turn = _swing_matrix(arm[..., 0], wr - sh_new) @ collar_turn
    world[:, ip] = collar_turn @ world[:, ip]
    world[:, ia] = arm_turn @ world[:, ia]
    world[:, ib] = arm_turn @ world[:, ib]
    pos[:, ib] = sh_new + (arm_turn @ (el - sh)[..., None])[..., 0]
    pos[:, ic] = sh_new + (arm_turn @ (wr - sh)[..., None])[..., 0]
    pos[:, ia] = sh_new
    local[:, ip] = np.swapaxes(world[:, parents[ip]], -1, -2) @ world[:, ip]
    local[:, ia] = np.swapaxes(world[:, ip], -1, -2) @ world[:, ia]
    local[:, ic] = np.swapaxes(world[:, ib], -1, -2) @ world[:, ic]


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def guard_legs(pos, goal, lock_weight, clearance=LEG_GUARD_M, max_push=LEG_GUARD_MAX_PUSH_M):
    """The legs kept apart by the foot IK (SSI 5.3's collision avoidance, done geometrically).

    Where a row's left and right thigh or shin segments come closer than `clearance`, the goals of
    the feet free to move are moved apart across the floor, the shortfall shared by how free each is
    (1 - its lock weight): the leg IK then swings the free leg around the other instead of through it.
    Moving an ankle moves a leg's closest point only part of the way (none at the hip, half at the
    knee), so the push is the shortfall over that part (at least 0.3), and at most `max_push`. A row
    with both feet planted is left to FootLock.separate. pos [N,J,3] the rows' poses before the IK;
    goal [N,2,3] their foot goals, moved in place; lock_weight [N,2]."""
    N = len(goal)
    L, R = pos[:N, LEG_SEGMENTS[0]], pos[:N, LEG_SEGMENTS[1]]          # [N, thigh/shin, end, 3]
    on_l, on_r, s, t = segment_closest(L[:, :, None, 0], L[:, :, None, 1], R[:, None, :, 0], R[:, None, :, 1])
    on_l, on_r, s, t = on_l.reshape(N, 4, 3), on_r.reshape(N, 4, 3), s.reshape(N, 4), t.reshape(N, 4)
    gap = np.linalg.norm(on_l - on_r, axis=-1)
    pair = gap.argmin(1)                        # left thigh/shin x right thigh/shin: pair // 2, pair % 2
    rows = np.arange(N)
    short = np.maximum(clearance - gap[rows, pair], 0.0)
    free = 1.0 - lock_weight[:N]
    total = free.sum(1)
    short[total < 1e-3] = 0.0
    if not short.any():
        return
    apart = on_l[rows, pair] - on_r[rows, pair]
    apart[:, 1] = 0.0
    hips = L[:, 0, 0] - R[:, 0, 0]              # the body's left (hip to hip), for legs on top of each other
    hips[:, 1] = 0.0
    apart = np.where(np.hypot(apart[:, 0], apart[:, 2])[:, None] > 0.01, apart, hips)
    apart /= np.maximum(np.linalg.norm(apart, axis=-1, keepdims=True), 1e-9)
    share = free / np.maximum(total, 1e-3)[:, None]
    along = np.stack([s[rows, pair], t[rows, pair]], 1)                     # [N, side]
    on_shin = np.stack([pair // 2, pair % 2], 1) == 1
    reach = np.maximum(np.where(on_shin, 0.5 + 0.5 * along, 0.5 * along), 0.3)
    push = np.minimum(short[:, None] * share / reach, max_push)             # [N, side]
    goal[:N, 0] += apart * push[:, :1]
    goal[:N, 1] -= apart * push[:, 1:]


class FootLock:
    """Per-sample, per-foot contact locks with a smooth release (LoBSTR 3.4.1).

    While a foot's contact probability (times edge.physics.support of its height: a foot in the air
    is not in contact) is above 0.5 its ankle is held where contact began, on the floor: a lock taken with the foot's lowest point within edge.physics.LOCK_SNAP_M of the floor is
    moved up or down onto it (a foot in contact stands on the floor, not above or under it). After
    release the IK weight eases from 1 to 0 over `release_frames` frames. A lock also lets go when the
    network's own ankle has moved more than `max_slip` metres from it across the floor: the contact
    was wrong, and holding on would drag the leg. Two planted feet stand at least `min_gap` apart across
    the floor (LOCK_GAP_M: legs closer than edge.physics.INTERSECT_M pass through each other): a lock
    taken closer to the other foot's is moved away from it (separate). `leg_guard`: the clearance
    guard_legs keeps between the legs while a foot is free (0: off).
    """

    def __init__(self, samples, feet=2, release_frames=10, max_slip=0.08, min_gap=LOCK_GAP_M, leg_guard=LEG_GUARD_M):
        self.release_frames, self.max_slip, self.min_gap = release_frames, max_slip, min_gap
        self.leg_guard = leg_guard
        self.lock_pos = np.zeros((samples, feet, 3))
        self.locked = np.zeros((samples, feet), bool)
        self.raw = np.zeros((samples, feet), bool)
        self.since_release = np.full((samples, feet), release_frames, dtype=np.float64)
        self.weight = np.zeros((samples, feet))

    def reset(self):
        self.locked[:] = False
        self.raw[:] = False
        self.since_release[:] = self.release_frames
        self.weight[:] = 0

    def update(self, contacts, ankle_pos, toe_drop=None):
        """contacts [B,2] probabilities, ankle_pos [B,2,3] -> IK targets [B,2,3] and weights [B,2].
        toe_drop [B,2]: each toe's height relative to its ankle (for the floor snap; None: no snap).

        B may be fewer than the samples allocated (adaptive N): the first B rows are updated."""
        B = len(contacts)
        lock_pos, locked, was_raw = self.lock_pos[:B], self.locked[:B], self.raw[:B]
        since, weight = self.since_release[:B], self.weight[:B]
        if toe_drop is not None:    # a foot in the air is not in contact, whatever the decoder says
            raw = contacts * support(lowest_point(ankle_pos[..., 1], toe_drop)) > 0.5
        else:
            raw = contacts > 0.5
        d = ankle_pos - lock_pos
        slipped = locked & (np.sqrt(d[..., 0] * d[..., 0] + d[..., 2] * d[..., 2]) > self.max_slip)
        # Lock on a new contact, or on a continuing one once an earlier release has fully eased out;
        # a lock taken mid-release starts where the foot is drawn, so the foot does not jump.
        start = raw & ~locked & (~was_raw | (weight == 0))
        drawn = ankle_pos + weight[..., None] * (lock_pos - ankle_pos)
        if toe_drop is not None:
            h = lowest_point(drawn[..., 1], toe_drop)
            drawn[..., 1] -= np.where(np.abs(h) <= LOCK_SNAP_M, h, 0.0)
        lock_pos[start] = drawn[start]
        locked[:] = (locked & raw & ~slipped) | start
        if start.any() and lock_pos.shape[1] == 2:
            self.separate(lock_pos, locked, start)
        was_raw[:] = raw
        since[locked] = 0
        since[~locked] += 1
        weight[:] = np.where(locked, 1.0, 1.0 - smoothstep(since / self.release_frames))
        return lock_pos, weight

    def separate(self, lock_pos, locked, start):
        """Two locked feet of a row closer across the floor than min_gap, one locked this frame, are
        moved apart to it along the line between them: the new lock, or both halfway when both are new."""
        d = lock_pos[:, 1] - lock_pos[:, 0]
        gap = np.hypot(d[:, 0], d[:, 2])
        rows = start.any(1) & locked.all(1) & (gap < self.min_gap)
        if not rows.any():
            return
        u = np.zeros((len(gap), 3))
        u[:, 0] = 1.0                               # on top of each other: apart along x
        far = gap > 1e-9
        u[far, 0], u[far, 2] = d[far, 0] / gap[far], d[far, 2] / gap[far]
        push = (self.min_gap - gap)[:, None] * u
        share_a = np.where(start[:, 0], np.where(start[:, 1], 0.5, 1.0), 0.0)[:, None]
        lock_pos[rows, 0] -= (share_a * push)[rows]
        lock_pos[rows, 1] += ((1.0 - share_a) * push)[rows]

    def copy_rows(self, src, dst):
        """Give rows `dst` the lock state of row `src` (a revived sample starts from the shown one)."""
        for a in (self.lock_pos, self.locked, self.raw, self.since_release, self.weight):
            a[dst] = a[src]
