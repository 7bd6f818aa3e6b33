"""Tracker signals synthesised from a canonical-skeleton motion, with the devices' noise.

One place for this: training, `edge eval` and the device simulator all call `synthesize` (the
signals themselves, edge.signals.Signals, are what the board's pipeline reads).
"""
from dataclasses import dataclass, fields

import numpy as np

from edge import quat
from edge.imus import IMU_JOINTS, ImuNoise, fade
from edge.signals import EYE_OFFSET, GRIP_OFFSET, Signals
from edge.skeleton import HEAD, JOINT, fk


def world_pose(rotations, root):
    """Canonical motion -> (world rotation matrices [T,J,3,3], world positions [T,J,3])."""
    return fk(quat.to_matrix(rotations), root)


def synthesize(rotations, root, fps, rng=None, noise=None):
    """Local rotations [T,J,4] and root positions [T,3] -> Signals. `noise` (a DeviceNoise) needs `rng`."""
    world_rot_m, pos = world_pose(rotations, root)
    return synthesize_from_pose(world_rot_m, pos, fps, rng, noise)


def synthesize_from_pose(world_rot_m, pos, fps, rng=None, noise=None):
    """World joint rotations [T,J,3,3] and positions [T,J,3] -> Signals."""
    world_rot = quat.from_matrix(world_rot_m)
    head_rot = world_rot[..., HEAD, :]
    wrists = [JOINT["l_wrist"], JOINT["r_wrist"]]
    hand_rot = world_rot[..., wrists, :]
    head_pos = pos[..., HEAD, :] + quat.rotate(head_rot, EYE_OFFSET)
    hand_pos = pos[..., wrists, :] + quat.rotate(hand_rot, GRIP_OFFSET)
    waist_rot = world_rot[..., 0, :]
    # Linear acceleration (gravity removed, as a BNO055 reports it) in the sensor frame.
    acc_world = np.gradient(np.gradient(pos[..., 0, :], axis=0), axis=0) * fps * fps
    sig = Signals(head_pos, head_rot, hand_pos, hand_rot, waist_rot, quat.rotate(quat.inv(waist_rot), acc_world),
                  world_rot[..., IMU_JOINTS, :])
    if noise is not None:
        sig = noise.apply(sig, fps, rng)
    return sig


def _smooth_noise(rng, shape, fps, std, corr_s):
    """AR(1) noise with stationary std `std` and correlation time `corr_s` along axis 0."""
    a = np.exp(-1.0 / (fps * corr_s))
    w = rng.standard_normal(shape) * std * np.sqrt(1 - a * a)
    out = np.empty(shape)
    out[0] = rng.standard_normal(shape[1:]) * std
    for t in range(1, shape[0]):
        out[t] = a * out[t - 1] + w[t]
    return out


def _random_small_rotations(rng, shape, max_deg):
    axis = rng.standard_normal(shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    ang = np.radians(rng.uniform(0, max_deg, shape))
    return quat.from_axis_angle(axis, ang)


@dataclass
class DeviceNoise:
    """Device noise for training (LoBSTR appendix: ~1 cm position, rotations up to 1.5 deg) plus IMU yaw drift."""
    pos_std_m: float = 0.01          # slowly wandering tracking offset
    pos_corr_s: float = 0.5
    jitter_std_m: float = 0.002      # per-sample optical/inside-out jitter
    rot_max_deg: float = 1.5
    yaw_offset_std_deg: float = 3.0  # residual heading error of the puck after calibration
    yaw_drift_deg_s: float = 0.5     # gyro-integration drift rate (std)

    def apply(self, s: Signals, fps, rng):
        # Axis 0 is time; any further leading axes are independent sequences (a training batch).
        T, batch = s.frames, s.waist_rot.shape[1:-1]
        off = _smooth_noise(rng, (T, *batch, 3, 3), fps, self.pos_std_m, self.pos_corr_s)
        off += rng.standard_normal((T, *batch, 3, 3)) * self.jitter_std_m
        head_pos = s.head_pos + off[..., 0, :]
        hand_pos = s.hand_pos + off[..., 1:, :]
        rot_noise = _random_small_rotations(rng, (T, *batch, 4), self.rot_max_deg)
        head_rot = quat.mul(rot_noise[..., 0, :], s.head_rot)
        hand_rot = quat.mul(rot_noise[..., 1:3, :], s.hand_rot)
        t = (np.arange(T) / fps).reshape((T,) + (1,) * len(batch))
        yaw = np.radians(rng.normal(0, self.yaw_offset_std_deg, batch) + rng.normal(0, self.yaw_drift_deg_s, batch) * t)
        waist_rot = quat.mul(quat.from_yaw(yaw), quat.mul(rot_noise[..., 3, :], s.waist_rot))
        acc = s.waist_acc + rng.standard_normal(s.waist_acc.shape) * 0.1
        return Signals(head_pos, quat.normalize(head_rot), hand_pos, quat.normalize(hand_rot),
                       quat.normalize(waist_rot), acc, s.imu_rot, s.imu_flag)


def wear(sig: Signals, worn, fps, rng=None, noise: ImuNoise = None, alive=None):
    """The extra IMUs `worn` ([7] mask, or [T,7] when the set changes) as the board sees them: with
    IMU noise (needs rng), and, when `alive` [T,7] says when each one is heard, held through silences
    and fading out and back in as the synchroniser does (edge.imus.fade)."""
    rot = sig.imu_rot if noise is None else noise.apply(sig.imu_rot, fps, rng)
    worn = np.broadcast_to(np.asarray(worn, float), sig.imu_flag.shape)
    flag = worn.copy()
    if alive is not None:
        flag, rot = fade(alive & (worn > 0), fps, rot)
        flag = flag * (worn > 0)
    out = Signals(**{f.name: getattr(sig, f.name) for f in fields(sig)})
    out.imu_rot, out.imu_flag = rot, flag
    return out
