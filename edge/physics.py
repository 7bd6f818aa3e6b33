"""Physical plausibility of a pose (SSI 3.2 and 5.3): the floor, the legs' clearance, and support.

One place for the geometry and the thresholds: the runtime's floor clamp (edge.pipeline), the
selection criterion (edge.criteria.PhysicalPlausibility, and its C twin) and the metrics (motion.metrics,
docs/metrics.md) read them from here. The floor is y = 0 in the world frame.
"""
import numpy as np

from edge.skeleton import ANKLES, FEET, JOINT, TOE_HEIGHT

PENETRATION_M = 0.02        # an ankle or toe this far below the floor sinks into it
INTERSECT_M = 0.10          # the two legs' thigh/shin segments closer than this pass through each other
FLOAT_M = 0.05              # a foot said to be in contact this far above the floor floats
ANKLE_HEIGHT = TOE_HEIGHT + 0.07    # the ankle joint's height above the floor in the rest pose
# The lowest the post-processing lets an ankle and a toe joint go (a flat foot has them at 0.09 and 0.02).
FLOOR_ANKLE = 0.07
FLOOR_TOE = 0.0
# A foot whose lowest point is more than SUPPORT_NONE_M above the floor cannot be standing on it: the
# contact the decoder reports fades out between SUPPORT_FULL_M and SUPPORT_NONE_M (edge.pipeline).
SUPPORT_FULL_M = 0.03
SUPPORT_NONE_M = 0.08
# A foot lock taken with the foot's lowest point within this of the floor is set on the floor (edge.ik.FootLock).
LOCK_SNAP_M = 0.12
# Two planted feet's locks stand at least this far apart across the floor (edge.ik.FootLock.separate):
# closer, the shins would be inside INTERSECT_M of each other.
LOCK_GAP_M = INTERSECT_M + 0.005
# The foot IK keeps a free leg this far from the other (edge.ik.guard_legs). Wider than INTERSECT_M because
# moving the ankle moves the closest point of a shin or thigh only part of the way (the hip stays put);
# chosen on val (model card, "Legs kept apart by the foot IK").
LEG_GUARD_M = 0.16
# The most the guard moves a foot goal in one frame (m).
LEG_GUARD_MAX_PUSH_M = 0.08
# Thigh (hip -> knee) and shin (knee -> ankle) of each leg: [side, segment, end]. C-contiguous int64: the
# compiled core reads it by address as [2][2][2] joint indices.
LEG_SEGMENTS = np.array([[[JOINT[f"{s}_hip"], JOINT[f"{s}_knee"]], [JOINT[f"{s}_knee"], JOINT[f"{s}_ankle"]]]
                         for s in "lr"], np.int64)


def segment_closest(p0, p1, q0, q1):
    """The closest points of segments p0-p1 and q0-q1 [...,3] and where they lie on them: (point on p,
    point on q, s, t), the points p0 + s (p1 - p0) and q0 + t (q1 - q0), s and t in [0, 1] (Ericson,
    Real-Time Collision Detection 5.1.9, with the parallel case handled)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = (d1 * d1).sum(-1), (d2 * d2).sum(-1), (d2 * r).sum(-1)
    c, b = (d1 * r).sum(-1), (d1 * d2).sum(-1)
    denom = a * e - b * b
    s = np.where(denom > 1e-12, np.clip((b * f - c * e) / np.where(denom > 1e-12, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / np.maximum(e, 1e-12)
    s = np.where(t < 0, np.clip(-c / np.maximum(a, 1e-12), 0, 1), np.where(t > 1, np.clip((b - c) / np.maximum(a, 1e-12), 0, 1), s))
    t = np.clip(t, 0, 1)
    return p0 + d1 * s[..., None], q0 + d2 * t[..., None], s, t


def segment_distance(p0, p1, q0, q1):
    """Closest distance between segments p0-p1 and q0-q1 [...,3] -> [...]."""
    a, b, _, _ = segment_closest(p0, p1, q0, q1)
    return np.linalg.norm(a - b, axis=-1)


def leg_pair_distances(pos):
    """The distance between each left-leg and each right-leg segment [...,4] (m): left thigh to right
    thigh, left thigh to right shin, left shin to right thigh, left shin to right shin."""
    L, R = pos[..., LEG_SEGMENTS[0], :], pos[..., LEG_SEGMENTS[1], :]      # [...,2,2,3]
    d = segment_distance(L[..., :, None, 0, :], L[..., :, None, 1, :], R[..., None, :, 0, :], R[..., None, :, 1, :])
    return d.reshape(d.shape[:-2] + (4,))


def leg_gap(pos):
    """The smallest distance between a left-leg and a right-leg segment (thighs and shins) [...] (m)."""
    return leg_pair_distances(pos).min(-1)


def foot_height(pos):
    """Each foot's lowest point above the floor [...,2] (m): the toe's or the ankle's height above where it
    stands in the rest pose, whichever is lower (a flat foot on the floor reads 0)."""
    return np.minimum(pos[..., FEET, 1] - TOE_HEIGHT, pos[..., ANKLES, 1] - ANKLE_HEIGHT)


def floor_lift(ankle_y, toe_drop_y):
    """How far a foot must rise so neither its ankle (at ankle_y) nor its toe (toe_drop_y below or above
    the ankle) is under the floor limits [...] (m, 0 when it is clear)."""
    return np.maximum(np.maximum(FLOOR_ANKLE - ankle_y, FLOOR_TOE - (ankle_y + toe_drop_y)), 0.0)


def lowest_point(ankle_y, toe_drop_y):
    """foot_height from an ankle's height and its toe's height relative to it [...] (m)."""
    return np.minimum(ankle_y + toe_drop_y - TOE_HEIGHT, ankle_y - ANKLE_HEIGHT)


def support(height):
    """How far a foot at this lowest-point height [...] can be bearing weight: 1 on the floor (up to
    SUPPORT_FULL_M), fading linearly to 0 at SUPPORT_NONE_M. A decoder contact is multiplied by it."""
    return np.clip((SUPPORT_NONE_M - height) / (SUPPORT_NONE_M - SUPPORT_FULL_M), 0.0, 1.0)
