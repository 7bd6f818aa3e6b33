"""Pose plausibility: the SSI autoencoder's view of a pose (SSI 3.2.1).

The autoencoder reads joint positions in the character frame and returns joint rotations; FK of
those rotations reconstructs the pose, and the mean lower-body joint distance is the score.
"""
import numpy as np

from edge import quat
from edge.features import heading, to_local


def local_pose(world_pos, pelvis_rot):
    """World positions [...,J,3] and pelvis orientation -> (positions in the character frame, pelvis rotation in it)."""
    yaw_q = heading(pelvis_rot)
    local = to_local(world_pos, world_pos[..., 0, :], yaw_q)
    return local, quat.mul(quat.inv(yaw_q), pelvis_rot)


class PlausibilityScorer:
    """Mean lower-body reconstruction error of poses under the autoencoder (metres)."""

    def __init__(self, autoencoder, threshold_m):
        self.autoencoder = autoencoder
        self.threshold = threshold_m

    def lower_body_error(self, world_pos, pelvis_rot):
        """world_pos [B,J,3], pelvis_rot [B,4] -> [B] error in metres."""
        from edge.skeleton import LOWER_BODY, NUM_PREDICTED, fk
        local, root_local = local_pose(world_pos, pelvis_rot)
        rot6d = self.autoencoder(local.reshape(len(local), -1))
        rots = np.empty(local.shape[:-1] + (3, 3))
        rots[:, 0] = quat.to_matrix(root_local)
        quat.matrix_from_6d(rot6d.reshape(len(local), NUM_PREDICTED, 6).astype(np.float64), out=rots[:, 1:])
        _, recon = fk(rots, local[:, 0])
        return np.linalg.norm(recon[:, LOWER_BODY] - local[:, LOWER_BODY], axis=-1).mean(-1)
