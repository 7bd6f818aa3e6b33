"""A heading observer for the extra body IMUs (issue #24, item 3).

A body IMU's heading (yaw about +Y) is off by what the T-pose calibration left and drifts as the gyro
integrates (edge.imus.ImuNoise: a fixed offset ~N(0, 3 deg) and a rate ~N(0, 0.5 deg/s); LoBSTR's
sensor noise, DragPoser's noisy sensors). The waist puck and the headset are the heading references
(in `edge eval` both are noise-free: edgetools.takes.load_take synthesises the signals without
DeviceNoise and edgetools.eval.take_signals noises only the seven extra IMUs).

Per worn IMU a two-state Kalman filter (heading offset, drift rate) is fed, at a reduced rate
(rate_hz), the heading of the IMU's raw orientation relative to the decoder's own estimate of that
segment: the shown sample's FK from the waist before fk_with_segments puts the IMU on the segment.
Only confident frames feed it: flag 1, the segment turning slowly, and an innovation the filter
finds plausible. Every frame, before the pipeline reads them, the IMUs' orientations are turned
back by the estimate at that frame (offset + rate * time since the last update): a yaw rotation of
seven quaternions in preallocated arrays.

The decoder reads the corrected IMU too, so its segment leans toward the IMU's remaining error; the
measurement is then biased toward the current estimate and the loop closes on the true offset more
slowly than a clean measurement would (the measured table is in the commit that added this file).
"""
import copy

import numpy as np

from edge import quat
from edge.imus import IMU_JOINTS, NUM_IMUS
from edge.skeleton import NUM_JOINTS


def heading_of(q):
    """The twist about +Y of unit quaternions q [...,4] (w,x,y,z), radians in (-pi, pi]: the heading
    part of a rotation, whatever the segment's direction (no gimbal at a vertical or level bone)."""
    return 2.0 * np.arctan2(q[..., 2], q[..., 0])


def wrap(angle):
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


class HeadingObserver:
    """Online heading offset and drift of each of the seven extra IMUs (edge.imus order).

    correct(t, imu_rot, imu_flag) every frame, in place, before the pipeline uses them; observe(t,
    segment_rot, imu_flag) at any frame with the decoder's own world orientations of the segments
    [7,4] (it updates every `every` frames and ignores the rest); observe_pipeline does the latter from
    a Pipeline's ring buffer. reset() at the start of a take."""

    def __init__(self, fps=60.0, rate_hz=10.0, offset_std_deg=3.0, drift_std_deg_s=0.5, measurement_std_deg=10.0,
                 drift_walk_deg_s2=0.02, max_turn_deg_s=120.0, gate_sigmas=3.0):
        self.fps = float(fps)
        self.every = max(1, int(round(fps / rate_hz)))
        # The prior is ImuNoise's: what a calibrated IMU starts with (LoBSTR's sensor noise, sec. 4.2).
        self.p0 = np.diag([np.radians(offset_std_deg) ** 2, np.radians(drift_std_deg_s) ** 2])
        self.r = np.radians(measurement_std_deg) ** 2
        self.q_rate = np.radians(drift_walk_deg_s2) ** 2      # the drift rate's random walk, per second
        self.max_turn = np.radians(max_turn_deg_s)
        self.gate = gate_sigmas
        K = NUM_IMUS
        self.offset, self.rate = np.zeros(K), np.zeros(K)    # the state at frame t_state (per IMU)
        self.t_state = np.zeros(K)
        self.P = np.zeros((K, 2, 2))
        self.raw = np.zeros((K, 4))                         # this frame's IMU orientations as they came
        self._prev_raw = np.zeros((K, 4))                   # at the last update (the turn gate)
        self._estimate = np.zeros(K)                        # the heading error at this frame, radians
        self._half_cos, self._half_sin = np.zeros(K), np.zeros(K)
        self._present = np.zeros(K)
        self._q = np.zeros((4, K))                          # scratch for the yaw product
        # observe_pipeline's FK of one decoder row, without the IMU override.
        self._fk = (np.zeros((1, NUM_JOINTS, 3, 3)), np.zeros((1, NUM_JOINTS, 3, 3)), np.zeros((1, NUM_JOINTS, 3)))
        self.reset()

    def reset(self):
        self.offset[:] = 0.0
        self.rate[:] = 0.0
        self.P[:] = self.p0
        self.t_state[:] = 0.0
        self.t_prev = -1
        self.updates = np.zeros(NUM_IMUS, np.int64)         # measurements taken, per IMU

    # ---- per frame
    def estimate(self, t, imu_flag):
        """Each IMU's heading error at frame t [7] radians: the filter's offset carried on by its rate
        while the IMU is fully present; a fading or lost one (flag < 1) holds its offset."""
        np.greater_equal(imu_flag, 1.0, out=self._present)
        np.subtract(t, self.t_state, out=self._estimate)
        self._estimate *= self._present
        self._estimate *= self.rate
        self._estimate *= 1.0 / self.fps
        self._estimate += self.offset
        return self._estimate

    def correct(self, t, imu_rot, imu_flag):
        """Turn the IMUs' orientations imu_rot [7,4] (w,x,y,z) back by the heading error estimated at
        frame t, in place; keeps the raw ones for observe. No arrays are made."""
        np.copyto(self.raw, imu_rot)
        est = self.estimate(t, imu_flag)
        c, s, q = self._half_cos, self._half_sin, self._q
        np.multiply(est, -0.5, out=s)                 # yaw(-est) = (cos(-est/2), 0, sin(-est/2), 0)
        np.cos(s, out=c)
        np.sin(s, out=s)
        w, x, y, z = self.raw[:, 0], self.raw[:, 1], self.raw[:, 2], self.raw[:, 3]
        # yaw(a) * (w,x,y,z) = (cw - sy, cx + sz, cy + sw, cz - sx) with (c, s) = (cos a/2, sin a/2)
        np.multiply(c, w, out=q[0])
        np.multiply(s, y, out=q[1])
        np.subtract(q[0], q[1], out=imu_rot[:, 0])
        np.multiply(c, x, out=q[0])
        np.multiply(s, z, out=q[1])
        np.add(q[0], q[1], out=imu_rot[:, 1])
        np.multiply(c, y, out=q[0])
        np.multiply(s, w, out=q[1])
        np.add(q[0], q[1], out=imu_rot[:, 2])
        np.multiply(c, z, out=q[0])
        np.multiply(s, x, out=q[1])
        np.subtract(q[0], q[1], out=imu_rot[:, 3])

    # ---- at the reduced rate
    def observe(self, t, segment_rot, imu_flag):
        """One measurement per worn, confident IMU at frame t: segment_rot [7,4] the decoder's own world
        orientations of the IMUs' segments (before any IMU override), against self.raw (correct's
        input at frame t). Frames between updates are ignored. Returns True when it updated."""
        if t % self.every:
            return False
        # A fading or lost IMU (flag < 1) is left as it is: no prediction, no measurement; its time
        # catches up when it is back (the drift went on while it was away).
        present = imu_flag >= 1.0
        dt = (t - self.t_state) / self.fps * present
        # Predict: offset += rate * dt, P = F P F' + Q (the rate walks slowly).
        self.offset += self.rate * dt
        P = self.P
        P[:, 0, 0] += dt * (2 * P[:, 0, 1] + dt * P[:, 1, 1])
        P[:, 0, 1] += dt * P[:, 1, 1]
        P[:, 1, 0] = P[:, 0, 1]
        P[:, 1, 1] += self.q_rate * dt
        self.t_state[present] = t
        # Gates: fully present, and turning slowly since the last update (the decoder lags a fast turn).
        ok = present.copy()
        if self.t_prev >= 0:
            turn = quat.angle(quat.mul(self.raw, quat.inv(self._prev_raw)))
            ok &= turn <= self.max_turn * (t - self.t_prev) / self.fps
        np.copyto(self._prev_raw, self.raw)
        self.t_prev = t
        z = heading_of(quat.mul(self.raw, quat.inv(segment_rot)))
        innovation = wrap(z - self.offset)
        s = P[:, 0, 0] + self.r
        ok &= innovation * innovation <= self.gate * self.gate * s
        for k in np.flatnonzero(ok):                # H = [1, 0]
            gain = P[k, :, 0] / s[k]
            self.offset[k] += gain[0] * innovation[k]
            self.rate[k] += gain[1] * innovation[k]
            P[k] -= np.outer(gain, P[k, 0])
            self.updates[k] += 1
        return True

    def observe_pipeline(self, pipe, s, row):
        """observe() with the decoder row `row` of ring slot s (the frame just stepped) as its estimate:
        FK from the waist without the IMU override (the path's forward_rows)."""
        if pipe.t % self.every:
            return False
        out = self._fk
        pipe.path.forward_rows(s, pipe.buffer.rot6d[s, row:row + 1], 1, False, out)
        return self.observe(pipe.t, quat.from_matrix(out[1][0, IMU_JOINTS]), pipe._in["imu_flag"])

    def correct_frame(self, pipe, sig):
        """correct() on a Pipeline's frame in (_frame_in's IMU views, which the compiled core reads), and
        the frame's Signals with those corrected orientations (what the numpy path reads): one object
        kept and refilled, no arrays made."""
        v = pipe._in
        self.correct(pipe.t, v["imu_rot"], v["imu_flag"])
        if getattr(self, "_sig_pipe", None) is not pipe:
            self._sig_pipe, self._imu_rot_view, self._sig = pipe, v["imu_rot"][None], copy.copy(sig)
        out = self._sig
        out.__dict__.update(sig.__dict__)
        out.imu_rot = self._imu_rot_view
        return out
