"""From tracker signals to the model's input, identically in training and on the board.

SSI section 3: the head, both hands and the waist, as positions and velocities in the character's
local frame (inverse waist yaw, X/Z relative to the waist, Y kept as height above the floor): 4 x 6 = 24. Then the extra
body IMUs (DragPoser's variable sensor sets, edge.imus): for each of the seven locations the 6D of its
orientation in the character frame, scaled by its presence flag, then the seven flags: 7 x 6 + 7 = 49.
The waist puck has no position, so the waist is placed under the head joint along the puck's
orientation using the calibrated pelvis-to-head length (`derive_waist_position`).
"""
import numpy as np

from edge import quat
from edge.signals import EYE_OFFSET, GRIP_OFFSET
from edge.skeleton import PELVIS_TO_HEAD

NUM_POINT_FEATURES = 24
NUM_IMU_FEATURES = 49
NUM_FEATURES = NUM_POINT_FEATURES + NUM_IMU_FEATURES     # what the CVAE reads
NUM_ORIENTATION_FEATURES = 18
# The decoder graph's input since v0.5: the CVAE's features, then the headset's and controllers' orientations,
# which only its upper-body head reads (models.nets.UpperBodyHead).
NUM_DECODER_FEATURES = NUM_FEATURES + NUM_ORIENTATION_FEATURES
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


def imu_features(imu_rot, imu_flag, yaw_q):
    """imu_rot [...,7,4] world orientations, imu_flag [...,7] presence 0..1, yaw_q [...,4] -> [...,49]:
    the 6D of each orientation in the character frame times its flag (an absent IMU reads 0), then the flags."""
    local = quat.to_matrix(quat.mul(quat.inv(yaw_q)[..., None, :], imu_rot))
    six = quat.matrix_to_6d(local) * imu_flag[..., None]
    return np.concatenate([six.reshape(six.shape[:-2] + (42,)), imu_flag], axis=-1)


def orientation_features(head_rot, hand_rot, yaw_q):
    """head_rot [...,4], hand_rot [...,2,4] world; yaw_q [...,4] -> [...,18]: the 6D of the headset's and
    the two controllers' orientations in the character frame (the decoder's upper-body head reads them)."""
    rot = np.concatenate([head_rot[..., None, :], hand_rot], axis=-2)
    six = quat.matrix_to_6d(quat.to_matrix(quat.mul(quat.inv(yaw_q)[..., None, :], rot)))
    return six.reshape(six.shape[:-2] + (18,))


def sequence_features(sig, fps, body_scale=1.0, n_features=NUM_FEATURES):
    """Features for a whole sequence [T,n_features]; the first frame's velocity is zero. n_features=24
    gives the 4-point features alone (the input of models trained before the extra IMUs); 91 adds the
    headset's and controllers' orientations (the decoder graphs since v0.5)."""
    pts, waist_rot = body_points(sig, body_scale)
    prev = np.concatenate([pts[:1], pts[:-1]], axis=0)
    yaw_q = heading(waist_rot)
    feats = features(pts, prev, yaw_q, fps)
    if n_features > NUM_POINT_FEATURES:
        feats = np.concatenate([feats, imu_features(sig.imu_rot, sig.imu_flag, yaw_q)], axis=-1)
    if n_features > NUM_FEATURES:
        feats = np.concatenate([feats, orientation_features(sig.head_rot, sig.hand_rot, yaw_q)], axis=-1)
    return feats, pts, yaw_q
