"""From tracker signals to the model's input, identically in training and on the board.

SSI section 3: the head, both hands and the waist, as positions and velocities in the character's
local frame (inverse waist yaw, X/Z relative to the waist, Y kept as height above the floor): 4 x 6 = 24.
The waist puck has no position, so the waist is placed under the head joint along the puck's
orientation using the calibrated pelvis-to-head length (`derive_waist_position`).
"""
import numpy as np

from edge import quat
from edge.signals import EYE_OFFSET, GRIP_OFFSET
from edge.skeleton import PELVIS_TO_HEAD

NUM_FEATURES = 24
_XZ = np.array([1.0, 0.0, 1.0])
POINTS = ("head", "l_wrist", "r_wrist", "pelvis")


def head_joint(head_pos, head_rot):
    return head_pos - quat.rotate(head_rot, EYE_OFFSET)


def wrist_joints(hand_pos, hand_rot):
    return hand_pos - quat.rotate(hand_rot, GRIP_OFFSET)


def derive_waist_position(head, waist_rot, body_scale=1.0):
    """Waist under the head joint: head minus the rest pelvis-to-head vector turned by the puck."""
    return head - quat.rotate(waist_rot, PELVIS_TO_HEAD * body_scale)


def body_points(sig, body_scale=1.0):
    """Signals -> world points [...,4,3] (head, wrists, pelvis) and the waist orientation."""
    head = head_joint(sig.head_pos, sig.head_rot)
    wrists = wrist_joints(sig.hand_pos, sig.hand_rot)
    waist = derive_waist_position(head, sig.waist_rot, body_scale)
    return np.concatenate([head[..., None, :], wrists, waist[..., None, :]], axis=-2), sig.waist_rot


def heading(waist_rot):
    """The character's yaw frame: a rotation about +Y facing where the waist faces."""
    return quat.from_yaw(quat.yaw(waist_rot))


def to_local(points, waist_pos, yaw_q):
    """World points [...,K,3] -> the character frame: X/Z relative to the waist, inverse waist yaw."""
    rel = points - waist_pos[..., None, :] * _XZ
    return quat.rotate(quat.inv(yaw_q)[..., None, :], rel)


def features(points, prev_points, yaw_q, fps):
    """points, prev_points [...,4,3] world; yaw_q [...,4] -> [...,24] (positions then velocities)."""
    local = to_local(points, points[..., 3, :], yaw_q)
    vel = quat.rotate(quat.inv(yaw_q)[..., None, :], (points - prev_points) * fps)
    return np.concatenate([local.reshape(local.shape[:-2] + (12,)), vel.reshape(vel.shape[:-2] + (12,))], axis=-1)


def sequence_features(sig, fps, body_scale=1.0):
    """Features for a whole sequence [T,24]; the first frame's velocity is zero."""
    pts, waist_rot = body_points(sig, body_scale)
    prev = np.concatenate([pts[:1], pts[:-1]], axis=0)
    yaw_q = heading(waist_rot)
    return features(pts, prev, yaw_q, fps), pts, yaw_q
