"""Sample-selection criteria for SSI (section 3.2 and 5.3). Each returns a cost per sample; lower is better.

They compose with weights (`Composite`); the pipeline runs them on the look-ahead frame, batched
over all N samples, after IK. Criteria that need the world (targets, obstacles, extra IMUs) read it
from the `FrameContext` the pipeline fills each frame.
"""
from dataclasses import dataclass, field

import numpy as np

from edge.skeleton import JOINT


@dataclass
class FrameContext:
    """What the criteria see for the frame being judged."""
    frame: int
    positions: np.ndarray       # [N,J,3] world, after IK
    world_rot: np.ndarray       # [N,J,3,3], or None unless a criterion sets needs_world_rot
    pelvis_rot: np.ndarray      # [N,3,3] each sample's pelvis rotation
    imu: dict = field(default_factory=dict)  # joint index -> measured world rotation [3,3] (extra trackers)
    ae_ready: object = None     # the PlausibilityScorer whose buffers already hold these poses (the pipeline's C call)


class Plausibility:
    """SSI 3.2.1: mean lower-body reconstruction error under the pose autoencoder (metres)."""
    name = "plausibility"

    def __init__(self, scorer, weight=1.0):
        self.scorer, self.weight = scorer, weight

    def cost(self, ctx):
        if ctx.ae_ready is self.scorer:
            return self.scorer.error_of_prepared(len(ctx.positions))
        return self.scorer.lower_body_error(ctx.positions, ctx.pelvis_rot)


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

    def __init__(self, weight=1.0):
        self.weight = weight

    def cost(self, ctx):
        if not ctx.imu:
            return np.zeros(len(ctx.positions))
        joints = np.fromiter(ctx.imu.keys(), dtype=int)
        measured = np.stack([ctx.imu[j] for j in joints])                     # [K,3,3]
        rel = np.swapaxes(ctx.world_rot[:, joints], -1, -2) @ measured         # [N,K,3,3]
        trace = np.trace(rel, axis1=-2, axis2=-1)
        return np.arccos(np.clip((trace - 1) / 2, -1, 1)).mean(-1)


class Composite:
    """Weighted sum of criteria."""

    def __init__(self, criteria):
        self.criteria = list(criteria)

    @property
    def needs_world_rot(self):
        """Whether any criterion reads FrameContext.world_rot (the pipeline then stores it)."""
        return any(getattr(c, "needs_world_rot", False) for c in self.criteria)

    def cost(self, ctx):
        if len(self.criteria) == 1 and self.criteria[0].weight == 1.0:
            return self.criteria[0].cost(ctx)         # the default (plausibility alone): no sum to build
        total = np.zeros(len(ctx.positions))
        for c in self.criteria:
            if c.weight:
                total += c.weight * c.cost(ctx)
        return total
