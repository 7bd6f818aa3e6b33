"""Tracker signals synthesised from a canonical-skeleton motion, with the devices' noise.

One place for this: training, `edge eval` and the device simulator all call `synthesize` (the
signals themselves, edge.signals.Signals, are what the board's pipeline reads).
"""
from dataclasses import dataclass, fields

import numpy as np

from edge import quat
from edge.imus import IMU_JOINTS, ImuNoise, axis_angle_deg, fade
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


def bend_hands(sig: Signals, fps, rng, flex_std_deg=20.0, dev_std_deg=10.0, waves=4, max_hz=1.0):
    """The controllers of `sig` with the hands bent at the wrist: a smoothly wandering flexion (about the
    hand's z, the palm's side axis) and deviation (about its y), each a sum of `waves` sines of random
    phase and frequency up to `max_hz` with the given std (smooth, as a hand moves: white noise here
    would be jerk no hand makes). The wrists stay where they are (the grips move with the hands), so
    the truth of the arms is the same: what a source whose hands stay in line with the forearm lacks
    (motion.hands)."""
    T, batch = sig.frames, sig.hand_rot.shape[1:-1]
    t = (np.arange(T) / fps).reshape((T,) + (1,) * (len(batch) + 1))

    def wander(std_deg):
        hz = rng.uniform(0.05, max_hz, (*batch, waves))
        phase = rng.uniform(0, 2 * np.pi, (*batch, waves))
        return np.radians(std_deg) * np.sqrt(2.0 / waves) * np.sin(2 * np.pi * hz * t + phase).sum(-1)

    flex, dev = wander(flex_std_deg), wander(dev_std_deg)
    zero = np.zeros_like(flex)
    bend = quat.mul(np.stack([np.cos(flex / 2), zero, zero, np.sin(flex / 2)], -1),
                    np.stack([np.cos(dev / 2), zero, np.sin(dev / 2), zero], -1))
    hand_rot = quat.normalize(quat.mul(sig.hand_rot, bend))
    hand_pos = sig.hand_pos + quat.rotate(hand_rot, GRIP_OFFSET) - quat.rotate(sig.hand_rot, GRIP_OFFSET)
    out = Signals(**{f.name: getattr(sig, f.name) for f in fields(sig)})
    out.hand_rot, out.hand_pos = hand_rot, hand_pos
    return out


def smooth_noise(first, steps, a):
    """AR(1) noise along axis 0 from standard normals: out[0] = first, out[t] = a out[t-1] + sqrt(1-a^2)
    steps[t] (stationary std 1; scale it)."""
    out = np.empty(steps.shape)
    out[0] = first
    w = steps * np.sqrt(1 - a * a)
    for t in range(1, len(steps)):
        out[t] = a * out[t - 1] + w[t]
    return out


@dataclass
class DeviceNoise:
    """Device noise for training (LoBSTR appendix: ~1 cm position, rotations up to 1.5 deg) plus IMU yaw drift."""
    pos_std_m: float = 0.01          # slowly wandering tracking offset
    pos_corr_s: float = 0.5
    jitter_std_m: float = 0.002      # per-sample optical/inside-out jitter
    rot_max_deg: float = 1.5
    yaw_offset_std_deg: float = 3.0  # residual heading error of the puck after calibration
    yaw_drift_deg_s: float = 0.5     # gyro-integration drift rate (std)

    def draw(self, rng, T, batch):
        """The random numbers of one application to T frames of `batch` sequences (a tuple of leading
        axes), as a dict: apply_drawn turns them into noise; models.batches draws the same on a device."""
        return {"wander": rng.standard_normal((T, *batch, 3, 3)), "wander0": rng.standard_normal((*batch, 3, 3)),
                "jitter": rng.standard_normal((T, *batch, 3, 3)),
                "rot_axis": rng.standard_normal((T, *batch, 4, 3)), "rot_deg": rng.uniform(0, self.rot_max_deg, (T, *batch, 4)),
                "yaw_offset_deg": rng.normal(0, self.yaw_offset_std_deg, batch),
                "yaw_drift_deg_s": rng.normal(0, self.yaw_drift_deg_s, batch),
                "acc": rng.standard_normal((T, *batch, 3))}

    def apply(self, s: Signals, fps, rng):
        # Axis 0 is time; any further leading axes are independent sequences (a training batch).
        return self.apply_drawn(s, fps, self.draw(rng, s.frames, s.waist_rot.shape[1:-1]))

    def apply_drawn(self, s: Signals, fps, d):
        T, batch = s.frames, s.waist_rot.shape[1:-1]
        off = smooth_noise(d["wander0"], d["wander"], np.exp(-1.0 / (fps * self.pos_corr_s))) * self.pos_std_m
        off += d["jitter"] * self.jitter_std_m
        head_pos = s.head_pos + off[..., 0, :]
        hand_pos = s.hand_pos + off[..., 1:, :]
        rot_noise = axis_angle_deg(d["rot_axis"], d["rot_deg"])
        head_rot = quat.mul(rot_noise[..., 0, :], s.head_rot)
        hand_rot = quat.mul(rot_noise[..., 1:3, :], s.hand_rot)
        t = (np.arange(T) / fps).reshape((T,) + (1,) * len(batch))
        yaw = np.radians(d["yaw_offset_deg"] + d["yaw_drift_deg_s"] * t)
        waist_rot = quat.mul(quat.from_yaw(yaw), quat.mul(rot_noise[..., 3, :], s.waist_rot))
        acc = s.waist_acc + d["acc"] * 0.1
        return Signals(head_pos, quat.normalize(head_rot), hand_pos, quat.normalize(hand_rot),
                       quat.normalize(waist_rot), acc, s.imu_rot, s.imu_flag)


def wear(sig: Signals, worn, fps, rng=None, noise: ImuNoise = None, alive=None, drawn=None):
    """The extra IMUs `worn` ([7] mask, or [T,7] when the set changes) as the board sees them: with
    IMU noise (needs rng, or the numbers `drawn` by noise.draw), and, when `alive` [T,7] says when each
    one is heard, held through silences and fading out and back in as the synchroniser does (edge.imus.fade)."""
    if noise is None:
        rot = sig.imu_rot
    else:
        rot = noise.apply_drawn(sig.imu_rot, fps, noise.draw(rng, sig.imu_rot.shape[:-1]) if drawn is None else drawn)
    worn = np.broadcast_to(np.asarray(worn, float), sig.imu_flag.shape)
    flag = worn.copy()
    if alive is not None:
        flag, rot = fade(alive & (worn > 0), fps, rot)
        flag = flag * (worn > 0)
    out = Signals(**{f.name: getattr(sig, f.name) for f in fields(sig)})
    out.imu_rot, out.imu_flag = rot, flag
    return out
