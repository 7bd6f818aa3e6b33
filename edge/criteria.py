"""Sample-selection criteria for SSI (section 3.2 and 5.3). Each returns a cost per sample; lower is better.

They compose with weights (`Composite`); the pipeline runs them on the look-ahead frame, batched
over all N samples, after IK. Criteria that need the world (targets, obstacles, extra IMUs) read it
from the `FrameContext` the pipeline fills each frame.
"""
import ctypes
from dataclasses import dataclass, field

import numpy as np

from edge import native
from edge.physics import ANKLE_HEIGHT, FLOAT_M, INTERSECT_M, LEG_SEGMENTS, foot_height, leg_gap
from edge.skeleton import ANKLES, FEET, JOINT, NUM_JOINTS, TOE_HEIGHT


@dataclass
class FrameContext:
    """What the criteria see for the frame being judged."""
    frame: int
    positions: np.ndarray       # [N,J,3] world, after IK
    world_rot: np.ndarray       # [N,J,3,3], or None unless a criterion sets needs_world_rot
    pelvis_rot: np.ndarray      # [N,3,3] each sample's pelvis rotation
    imu: dict = field(default_factory=dict)  # joint index -> measured world rotation [3,3] (extra trackers)
    ae_ready: object = None     # the PlausibilityScorer whose buffers already hold these poses (the pipeline's C call)
    contacts: np.ndarray = None     # [N,2] each sample's foot-contact probabilities (the decoder's)
    floor_lift: np.ndarray = None   # [N,2] how far the floor clamp lifted each sample's feet (m)
    imu_weight: dict = field(default_factory=dict)  # joint index -> the IMU's presence flag (0..1)


class Plausibility:
    """SSI 3.2.1: mean lower-body reconstruction error under the pose autoencoder (metres)."""
    name = "plausibility"

    def __init__(self, scorer, weight=1.0):
        self.scorer, self.weight = scorer, weight

    def cost(self, ctx):
        if ctx.ae_ready is self.scorer:
            return self.scorer.error_of_prepared(len(ctx.positions))
        return self.scorer.lower_body_error(ctx.positions, ctx.pelvis_rot)


class PhysicalPlausibility:
    """SSI 3.2 and 5.3's constraints as a cost in metres: how far the floor had to lift the sample's
    feet (its raw legs went into the floor), how far its thigh and shin segments come inside 10 cm of
    the other leg's (legs through each other), and how far above 5 cm a foot is while the sample says
    it is in contact (contact without support). Batched over samples; the compiled core's
    ep_physical_cost computes the same when it is there."""
    name = "physical"

    def __init__(self, weight=1.0, floor=1.0, legs=1.0, support=1.0, use_native=True, clearance=INTERSECT_M):
        self._native = native.load() if use_native else None
        self._feet = np.ascontiguousarray(np.concatenate([FEET, ANKLES]), np.int64)
        self._out = np.zeros(128)
        # The compiled core's copy of the settings (None without it); the term weights below write through.
        self.params = None
        if self._native:
            self.params = native.PhysicalParams(native.addr(LEG_SEGMENTS), native.addr(self._feet), clearance, FLOAT_M,
                                                TOE_HEIGHT, ANKLE_HEIGHT, floor, legs, support)
        self.weight, self.floor, self.legs, self.support = weight, floor, legs, support
        # Legs closer than `clearance` cost: above INTERSECT_M, a sample pays before its legs cross (with
        # no look-ahead, the switch then starts before the fault shows instead of after).
        self.clearance = clearance

    # The three terms' weights, kept in the compiled core's params as they change (a tuning run sets them).
    floor = property(lambda self: self._floor, lambda self, w: self._set("floor", w))
    legs = property(lambda self: self._legs, lambda self, w: self._set("legs", w))
    support = property(lambda self: self._support, lambda self, w: self._set("support", w))

    def _set(self, term, w):
        setattr(self, "_" + term, float(w))
        if self.params is not None:
            setattr(self.params, "w_" + term, float(w))

    def cost(self, ctx):
        N, pos = len(ctx.positions), ctx.positions
        lift = np.zeros((N, 2)) if ctx.floor_lift is None else ctx.floor_lift
        contacts = np.zeros((N, 2), np.float32) if ctx.contacts is None else ctx.contacts
        if (self._native and N <= len(self._out) and pos.flags.c_contiguous and lift.flags.c_contiguous
                and contacts.dtype == np.float32 and contacts.flags.c_contiguous and pos.shape[1] == NUM_JOINTS):
            a = native.addr
            self._native.ep_physical_cost(N, NUM_JOINTS, a(pos), a(contacts), a(lift), ctypes.byref(self.params),
                                          a(self._out))
            return self._out[:N]
        legs = np.maximum(self.clearance - leg_gap(pos), 0.0)
        support = ((contacts > 0.5) * np.maximum(foot_height(pos) - FLOAT_M, 0.0)).sum(-1)
        return self.floor * lift.sum(-1) + self.legs * legs + self.support * support


class TargetHit:
    """SSI eq. 3: distance from an end-effector to a target point, while a target is active.

    `targets` maps a frame index to a target position [3] (or None when no target is active).
    """
    name = "target"

    def __init__(self, joint, targets, weight=1.0):
        self.joint = JOINT[joint] if isinstance(joint, str) else int(joint)
        self.targets, self.weight = targets, weight

    def cost(self, ctx):
        target = self.targets(ctx.frame)
        if target is None:
            return np.zeros(len(ctx.positions))
        return np.linalg.norm(ctx.positions[:, self.joint] - target, axis=-1)


class CollisionAvoid:
    """SSI eq. 4, as a penetration cost: how deep joints go into spherical obstacles (metres, summed)."""
    name = "collision"

    def __init__(self, centers, radii, joints=("l_knee", "l_ankle", "l_toe", "r_knee", "r_ankle", "r_toe"), weight=1.0):
        self.centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        self.radii = np.asarray(radii, dtype=np.float64).reshape(-1)
        self.joints = np.array([JOINT[j] if isinstance(j, str) else j for j in joints])
        self.weight = weight

    def penetration(self, positions):
        d = np.linalg.norm(positions[:, self.joints, None, :] - self.centers, axis=-1)   # [N,K,O]
        return np.maximum(self.radii - d, 0.0).sum(axis=(1, 2))

    def cost(self, ctx):
        return self.penetration(ctx.positions)


class SensorAgreement:
    """Prefer samples whose joint orientations match extra IMU trackers (a zero-order form of DragPoser's
    constraint losses): mean rotation angle (radians) between each sample's joint and the measurement."""
    name = "sensors"
    needs_world_rot = True      # the pipeline stores every joint's world rotation only when asked
    needs_imu = True            # ... and hands it the frame's extra IMUs (edge.imus), weighted by presence

    def __init__(self, weight=1.0):
        self.weight = weight

    def cost(self, ctx):
        if not ctx.imu:
            return np.zeros(len(ctx.positions))
        joints = np.fromiter(ctx.imu.keys(), dtype=int)
        measured = np.stack([ctx.imu[j] for j in joints])                     # [K,3,3]
        w = np.array([ctx.imu_weight.get(j, 1.0) for j in joints])            # a fading IMU counts less
        rel = np.swapaxes(ctx.world_rot[:, joints], -1, -2) @ measured         # [N,K,3,3]
        trace = np.trace(rel, axis1=-2, axis2=-1)
        return (np.arccos(np.clip((trace - 1) / 2, -1, 1)) * w).sum(-1) / max(w.sum(), 1e-9)


class Composite:
    """Weighted sum of criteria."""

    def __init__(self, criteria):
        self.criteria = list(criteria)

    @property
    def needs_world_rot(self):
        """Whether any criterion reads FrameContext.world_rot (the pipeline then stores it)."""
        return any(getattr(c, "needs_world_rot", False) for c in self.criteria)

    @property
    def needs_imu(self):
        """Whether any criterion reads FrameContext.imu (the pipeline then fills it)."""
        return any(getattr(c, "needs_imu", False) for c in self.criteria)

    def cost(self, ctx):
        if len(self.criteria) == 1 and self.criteria[0].weight == 1.0:
            return self.criteria[0].cost(ctx)         # the default (plausibility alone): no sum to build
        total = np.zeros(len(ctx.positions))
        for c in self.criteria:
            if c.weight:
                total += c.weight * c.cost(ctx)
        return total
