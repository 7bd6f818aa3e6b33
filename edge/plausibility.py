"""Pose plausibility: the SSI autoencoder's view of a pose (SSI 3.2.1).

The autoencoder reads joint positions in the character frame and returns joint rotations; FK of
those rotations reconstructs the pose, and the mean lower-body joint distance is the score.
"""
import numpy as np

from edge import native, quat
from edge.skeleton import LEGS, NUM_JOINTS, NUM_PREDICTED, OFFSETS, fk_legs

# Rows of the autoencoder's rotation output (joint index - 1) for hip, knee and ankle of each leg.
_LEG_ROWS = LEGS[:, :3] - 1


def yaw_matrix(rot_m):
    """Heading-only rotation [...,3,3] of rotation matrices: about +Y, facing their +Z axis."""
    fwd = rot_m[..., :, 2]
    theta = np.arctan2(fwd[..., 0], fwd[..., 2])
    c, s = np.cos(theta), np.sin(theta)
    out = np.zeros(rot_m.shape)
    out[..., 0, 0], out[..., 0, 2], out[..., 1, 1], out[..., 2, 0], out[..., 2, 2] = c, s, 1.0, -s, c
    return out


def local_pose(world_pos, pelvis_rot_m):
    """World positions [...,J,3] and pelvis rotation [...,3,3] -> (positions in the character frame, pelvis rotation in it)."""
    yaw = yaw_matrix(pelvis_rot_m)
    yaw_t = np.swapaxes(yaw, -1, -2)
    rel = world_pos - world_pos[..., :1, :] * np.array([1.0, 0.0, 1.0])
    local = (yaw_t[..., None, :, :] @ rel[..., None])[..., 0]
    return local, yaw_t @ pelvis_rot_m


class PlausibilityScorer:
    """Mean lower-body reconstruction error of poses under the autoencoder (metres).

    A batch of exactly the autoencoder's bound rows (the pipeline's N samples, every frame) goes
    through the compiled core into preallocated buffers, and the result is a view that the next call
    overwrites; any other batch (whole clips in `edge eval`) takes the numpy path.
    """

    def __init__(self, autoencoder, threshold_m, use_native=True):
        self.autoencoder = autoencoder
        self.threshold = threshold_m
        self._native = native.load() if use_native and autoencoder.capacity else None
        if self._native:
            cap = autoencoder.capacity
            self._local = np.zeros((cap, NUM_JOINTS, 3))
            self._root_local = np.zeros((cap, 3, 3))
            self._err = np.zeros(cap)
            self._legs = np.ascontiguousarray(LEGS, np.int64)
            self._leg_rows = np.ascontiguousarray(_LEG_ROWS, np.int64)
            self._a = {k: native.addr(v) for k, v in (("local", self._local), ("root_local", self._root_local),
                       ("err", self._err), ("legs", self._legs), ("leg_rows", self._leg_rows), ("offsets", OFFSETS),
                       ("inp", autoencoder.inp), ("out", autoencoder.out))}

    def lower_body_error(self, world_pos, pelvis_rot_m):
        """world_pos [B,J,3], pelvis_rot_m [B,3,3] -> [B] error in metres."""
        B = len(world_pos)
        # The compiled core takes the caller's arrays only as it needs them (checked on every call: this
        # is public); anything else takes the numpy path, which accepts any layout and float dtype.
        if (self._native and B == self.autoencoder.rows and isinstance(world_pos, np.ndarray)
                and world_pos.dtype == np.float64 and world_pos.shape[1:] == (NUM_JOINTS, 3)
                and world_pos.flags.c_contiguous and isinstance(pelvis_rot_m, np.ndarray)
                and pelvis_rot_m.dtype == np.float64 and pelvis_rot_m.shape[-2:] == (3, 3)
                and pelvis_rot_m.shape[0] == B and pelvis_rot_m[0].flags.c_contiguous):
            return self._lower_body_error_native(B, world_pos, pelvis_rot_m)
        local, root_local = local_pose(world_pos, pelvis_rot_m)
        B = len(local)
        rot6d = self.autoencoder(local.reshape(B, NUM_JOINTS * 3)).reshape(B, NUM_PREDICTED, 6)
        legs = quat.matrix_from_6d(rot6d[:, _LEG_ROWS].astype(np.float64))     # [B,2,3,3,3]
        recon = fk_legs(root_local, local[:, 0], legs)                      # [B,2,4,3]
        d = recon - local[:, LEGS]
        return np.sqrt(np.einsum("...i,...i->...", d, d)).mean(axis=(1, 2))

    def _lower_body_error_native(self, B, world_pos, pelvis_rot_m):
        pelvis, stride = native.rows(pelvis_rot_m, 2)
        a = self._a
        self._native.ep_local_pose(B, NUM_JOINTS, native.addr(world_pos), pelvis, stride, a["local"], a["inp"],
                                   a["root_local"])
        return self.error_of_prepared(B)

    def error_of_prepared(self, B):
        """lower_body_error of B poses whose character-frame positions someone else has already put in
        this scorer's buffers (the pipeline's one C call per frame does, into `buffers()`)."""
        lib, ae, a = self._native, self.autoencoder, self._a
        ae.run()
        lib.ep_leg_error(B, NUM_JOINTS, a["out"], ae.out.shape[1], a["leg_rows"], a["legs"], a["offsets"], a["local"],
                         a["root_local"], a["err"])
        return self._err[:B]

    def buffers(self):
        """Addresses of (autoencoder input, character-frame positions, pelvis rotations) to prepare, or None."""
        a = self._a
        return (a["inp"], a["local"], a["root_local"]) if self._native else None

    def leg_error_buffers(self):
        """Addresses of (the legs' rows of the autoencoder's output, the leg joints, the error [B] it
        writes) for a caller that scores in its own C call (edge.frame_compiled's fused selection), or None."""
        a = self._a
        return (a["leg_rows"], a["legs"], a["err"]) if self._native else None
