"""Pose outputs other tools consume: VMC protocol, VRChat OSC trackers, BVH recordings.

    from firmware_bridge.outputs.vmc import VmcSender              # VSeeFace, EVMC4U, VMC4B, ...
    from firmware_bridge.outputs.vrchat import VrchatSender        # VRChat's OSC trackers
    from firmware_bridge.outputs.bvh_writer import BvhWriter       # Blender, MotionBuilder, ...

    with VmcSender() as vmc, BvhWriter("take.bvh", fps=60) as bvh:
        for pose in poses:                                         # edge.frame.Pose
            vmc.send(pose)
            bvh.send(pose)

Each is a PoseSink: `send(pose)` every frame, `close()` at the end; the board's service drives them all
through those two calls.

`osc` is the wire format both UDP outputs share. This module holds the one conversion both share:
edgepose's frame to Unity's.

edgepose: right-handed, Y-up, metres; the character faces +Z with its left at +X.
Unity:    left-handed,  Y-up, metres; the character faces +Z with its left at -X.

Both keep up and forward, so the change of frame is the mirror S = diag(-1, 1, 1):
- positions:  p_unity = S p                (negate X);
- rotations:  R_unity = S R S              (negate the entries of row 0 and of column 0, not both);
- quaternions (w, x, y, z) -> (w, x, -y, -z): a rotation axis is a pseudovector, so mirroring
  X flips the axis's Y and Z and keeps the angle. Unity's Quaternion has the same algebra as ours
  (q = cos(a/2), sin(a/2) * axis), so to_matrix of the result is exactly S R S.

Example: the left upper arm swung from pointing left to pointing forward is R = Ry(-90 deg) here,
(w, y) = (0.707, -0.707); in Unity it is (x, y, z, w) = (0, 0.707, 0, 0.707) = Quaternion.Euler(0, 90, 0),
which takes Unity's left (-1, 0, 0) to forward (0, 0, 1).
"""
from abc import ABC, abstractmethod

import numpy as np


class PoseSink(ABC):
    """A pose output: one call a frame, one at the end. A sink never raises into the tracking loop for
    a receiver that is absent or slow (it counts and drops); it may raise OSError or ValueError for a
    local fault (a full disk), which the service counts."""

    @abstractmethod
    def send(self, pose):
        """Output one edge.frame.Pose."""

    @abstractmethod
    def close(self):
        """Finish (a recording's frame count) and release what the sink holds."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

from edge import native

MIRROR_X = np.array([-1.0, 1.0, 1.0])
# S R S elementwise: entry (i, j) is multiplied by s_i * s_j.
MIRROR_X_MATRIX_SIGNS = np.outer(MIRROR_X, MIRROR_X)
# Quaternion (w, x, y, z) -> Unity's (x, y, z, w) with Y and Z negated.
UNITY_XYZW_ORDER = np.array([1, 2, 3, 0])
UNITY_XYZW_SIGNS = np.array([1.0, -1.0, -1.0, 1.0])


def to_unity_position(p):
    """Positions [...,3] in our frame -> Unity's (negate X)."""
    return p * MIRROR_X


def to_unity_matrix(m):
    """Rotation matrices [...,3,3] in our frame -> Unity's (S R S)."""
    return m * MIRROR_X_MATRIX_SIGNS


def to_unity_quaternion(m):
    """Rotation matrices [...,3,3] in our frame -> Unity quaternions [...,4] ordered (x, y, z, w)."""
    return native.from_matrix(m)[..., UNITY_XYZW_ORDER] * UNITY_XYZW_SIGNS
