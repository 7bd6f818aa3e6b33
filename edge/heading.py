"""A heading observer for the extra body IMUs (issue #24, item 3).

A body IMU's heading (yaw about +Y) is off by what the T-pose calibration left and drifts as the gyro
integrates (edge.imus.ImuNoise: a fixed offset ~N(0, 3 deg) and a rate ~N(0, 0.5 deg/s); LoBSTR's
sensor noise, DragPoser's noisy sensors). The waist puck and the headset are the heading references
(in `edge eval` both are noise-free: motion.takes.load_take synthesises the signals without
DeviceNoise and motion.evaluate.take_signals noises only the seven extra IMUs).

Per worn IMU a three-state Kalman filter (the IMU's heading offset, the reference's bias over the
take, the drift rate) is fed, at a reduced rate (rate_hz), the heading of the IMU's raw orientation
relative to a reference: by default the body (a leg segment faces where the waist puck faces, the
chest halfway between the puck and the headset, up to a mean and a per-take spread measured on
train), or the decoder's own segment (the shown sample's FK from the waist before fk_with_segments
puts the IMU on it). Only confident frames feed it: flag 1, the IMU turning slowly, and an
innovation the filter finds plausible. A constant offset cannot be told from the body's own bias
(the filter takes the share its priors give); the drift shows as the measurement moving over seconds
and comes out nearly whole. Every frame, before the pipeline reads them, the IMUs' orientations are
turned back by the last estimate: a yaw rotation of seven quaternions in preallocated arrays (six
ufunc calls into the pipeline's own input array).

Measured on val (N=1 int8, all seven IMUs, bench/sensor_sets.py): mpjpe 3.299 cm without, 2.899
against the body, 2.997 against the decoder, 2.849 with no heading error at all. The decoder knows a
leg segment's heading worse than the pelvis does (its clip-mean error spreads 5-23 deg over the
seven, the pelvis relation's 2-12), and it reads the corrected IMU, so it leans toward the IMU's
remaining error.
"""
import copy
from dataclasses import dataclass, fields

import numpy as np

from edge import quat
from edge.imus import IMU_JOINTS, NUM_IMUS
from edge.settings import settings_from
from edge.signals import Signals
from edge.skeleton import NUM_JOINTS


_SWAP_SIGNS = np.array([-1.0, 1.0, 1.0, -1.0])


def heading_of(q):
    """The twist about +Y of unit quaternions q [...,4] (w,x,y,z), radians in (-pi, pi]: the heading
    part of a rotation, whatever the segment's direction (no gimbal at a vertical or level bone)."""
    return 2.0 * np.arctan2(q[..., 2], q[..., 0])


def wrap(angle):
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def body_references(waist_rot, head_rot, out=None):
    """The trusted reference orientation [7,4] for each extra IMU's heading: the waist puck for the
    legs, and for the chest the waist turned halfway to the headset's heading."""
    out = np.empty((NUM_IMUS, 4)) if out is None else out
    out[:] = waist_rot
    out[0] = quat.mul(quat.from_yaw(0.5 * wrap(heading_of(quat.mul(head_rot, quat.inv(waist_rot))))), waist_rot)
    return out


# The segment's heading relative to its body reference, in degrees: its mean and its spread of clip
# means over 150 train clips (clean signals; edge.imus order: chest, thighs, shins, feet). A standing
# or walking body's legs face roughly where the pelvis faces (the feet turn out a little); the chest
# faces halfway between the pelvis and the headset (as torso_segments in edge.pipeline builds the
# spine), spread 1.9 deg where the pelvis alone gives 3.8.
PELVIS_RELATIVE_MEAN_DEG = np.array([0.0, -0.1, 1.7, -0.2, 0.3, 3.1, -7.0])
PELVIS_RELATIVE_SPREAD_DEG = np.array([1.9, 6.4, 6.9, 3.2, 3.5, 7.5, 6.3])
# The shown sample's own segment headings against the truth, spread of clip means over 40 val clips
# with all seven IMUs worn (N=1 int8): the decoder knows the legs' headings worse than the pelvis does.
DECODER_SPREAD_DEG = np.array([5.2, 9.0, 5.4, 10.3, 15.7, 23.4, 18.3])
# How far one 10 Hz measurement strays, degrees: the feet wander most about their take's mean (chosen
# on the corrected headings' rms over 120 train clips: 6 for all gave the feet more error than none).
MEASUREMENT_STD_DEG = np.array([6.0, 6.0, 6.0, 6.0, 6.0, 12.0, 12.0])


SIGNAL_FIELDS = tuple(f.name for f in fields(Signals))


@dataclass(frozen=True)
class HeadingSettings:
    """The heading observer's filter: how often it updates, what it takes as the body's heading
    ("pelvis": the waist IMU's, or "decoder": the shown sample's segments), its priors (degrees, per
    IMU or one for all), the random walks of bias and drift, and the gates on turns and outliers."""
    rate_hz: float = 10.0
    reference: str = "pelvis"
    offset_std_deg: float = 3.0
    drift_std_deg_s: float = 0.5
    bias_std_deg: object = None          # a number, one per IMU, or None: the reference's own spread
    measurement_std_deg: object = tuple(MEASUREMENT_STD_DEG)     # per IMU
    bias_walk_deg_s: float = 0.5
    drift_walk_deg_s2: float = 0.02
    max_turn_deg_s: float = 120.0
    gate_sigmas: float = 3.0

    @classmethod
    def parse(cls, value):
        """None/False (off), True (the defaults), a dict of fields, or HeadingSettings."""
        return settings_from(cls, value, "heading")


class HeadingObserver:
    """Online heading offset and drift of each of the seven extra IMUs (edge.imus order).

    correct(imu_rot) every frame, in place, before the pipeline uses them; observe(t,
    reference_rot, imu_flag) with the reference's world orientations [7,4] of the IMUs' segments (it
    updates every `every` frames and ignores the rest). The reference is the body ("pelvis": each leg
    segment is taken to face where the waist puck faces, the chest halfway between the puck and the
    headset, up to a mean and a per-take bias; body_references) or the decoder
    ("decoder": the shown sample's own segments, FK without the IMU override); observe_frame takes
    either from a Pipeline. reset() at the start of a take.

    State per IMU: the IMU's heading offset o, the reference's bias b over the take (how far this
    body's segment faces off the reference on average), the drift rate r; the measurement is
    o + b + noise, so the filter splits what it sees between o and b by their priors, and the rate
    comes from how the measurement moves over seconds."""

    def __init__(self, fps=60.0, settings=None, decoder_fk=None):
        s = self.settings = HeadingSettings() if settings is None else settings
        if s.reference not in ("pelvis", "decoder"):
            raise ValueError(f"reference must be 'pelvis' or 'decoder', got {s.reference!r}")
        self.fps, self.reference = float(fps), s.reference
        self.every = max(1, int(round(fps / s.rate_hz)))
        K = NUM_IMUS
        bias_std_deg = s.bias_std_deg
        if bias_std_deg is None:
            bias_std_deg = PELVIS_RELATIVE_SPREAD_DEG if s.reference == "pelvis" else DECODER_SPREAD_DEG
        self.mean = np.radians(PELVIS_RELATIVE_MEAN_DEG) if s.reference == "pelvis" else np.zeros(K)
        # The prior of o and r is ImuNoise's, what a calibrated IMU starts with (LoBSTR's sensor noise).
        self.p0 = np.zeros((K, 3, 3))
        self.p0[:, 0, 0] = np.radians(s.offset_std_deg) ** 2
        self.p0[:, 1, 1] = np.radians(np.broadcast_to(bias_std_deg, (K,))) ** 2
        self.p0[:, 2, 2] = np.radians(s.drift_std_deg_s) ** 2
        self.r = np.radians(np.broadcast_to(np.asarray(s.measurement_std_deg, float), (K,))) ** 2
        self.q_bias = np.radians(s.bias_walk_deg_s) ** 2        # the bias wanders as the activity changes, per second
        self.q_rate = np.radians(s.drift_walk_deg_s2) ** 2      # the drift rate's random walk, per second
        self.max_turn = np.radians(s.max_turn_deg_s)
        self.gate = s.gate_sigmas
        self.x = np.zeros((K, 3))                           # (o, b, r) at frame t_state, per IMU
        self.offset, self.rate = self.x[:, 0], self.x[:, 2]
        self.t_state = np.zeros(K)
        self.P = np.zeros((K, 3, 3))
        self.raw = np.zeros((K, 4))                         # this frame's IMU orientations as they came
        self._prev_raw = np.zeros((K, 4))                   # at the last update (the turn gate)
        self._turn_cos, self._turn_sin = np.zeros((K, 4)), np.zeros((K, 4))   # yaw(-offset), laid out for correct
        self._swapped = np.zeros((K, 4))
        self._waist_y = np.zeros(4)
        self._raw_views = (self.raw[:, :2], self.raw[:, 2:])
        self._swapped_views = (self._swapped[:, :2], self._swapped[:, 2:])
        # observe_frame's FK of one decoder row, without the IMU override (edge.frame.RowFk over the
        # pipeline's frame path and ring; needed only with the decoder as the reference).
        self.decoder_fk = decoder_fk
        self._sig, self._imu_rot_view = None, None
        self._fk = (np.zeros((1, NUM_JOINTS, 3, 3)), np.zeros((1, NUM_JOINTS, 3, 3)), np.zeros((1, NUM_JOINTS, 3)))
        self.reset()

    def reset(self):
        self.x[:] = 0.0
        self.P[:] = self.p0
        self.t_state[:] = 0.0
        self.t_prev = -1
        self.updates = np.zeros(NUM_IMUS, np.int64)         # measurements taken, per IMU
        self.apply_estimate()

    # ---- per frame
    def correct(self, imu_rot):
        """Turn this frame's IMU orientations imu_rot [7,4] (w,x,y,z) back by the heading errors last
        estimated, in place; keeps the raw ones for observe. Six ufunc calls into preallocated arrays,
        no arrays made. Between updates the correction holds (the drift moves it by rate / rate_hz:
        0.05 deg at 0.5 deg/s and 10 Hz)."""
        raw, swapped = self.raw, self._swapped
        np.copyto(raw, imu_rot)
        np.copyto(self._swapped_views[0], self._raw_views[1])     # (y, z, w, x)
        np.copyto(self._swapped_views[1], self._raw_views[0])
        np.multiply(self._turn_cos, raw, out=imu_rot)
        np.multiply(self._turn_sin, swapped, out=swapped)
        np.add(imu_rot, swapped, out=imu_rot)

    def apply_estimate(self):
        """The correction correct() applies from now on, yaw(-offset) on the left of each orientation:
        yaw(a) * (w,x,y,z) = (cw - sy, cx + sz, cy + sw, cz - sx) with (c, s) = (cos a/2, sin a/2), laid
        out as c * (w,x,y,z) + s * (-1, 1, 1, -1) * (y,z,w,x)."""
        self._turn_cos[:] = np.cos(-0.5 * self.offset)[:, None]
        self._turn_sin[:] = np.sin(-0.5 * self.offset)[:, None] * _SWAP_SIGNS

    # ---- at the reduced rate
    def observe(self, t, reference_rot, imu_flag):
        """One measurement per worn, confident IMU at frame t: reference_rot [7,4] (or [4], one for all)
        the reference's world orientations of the IMUs' segments, against self.raw (correct's input at
        frame t). Frames between updates are ignored. Returns True when it updated."""
        if t % self.every:
            return False
        return self.observe_heading(t, heading_of(quat.mul(self.raw, quat.inv(reference_rot))), imu_flag)

    def observe_heading(self, t, relative_heading, imu_flag):
        """observe() given each raw IMU's heading relative to its reference [7] radians (heading_of(raw *
        reference^-1)), at an update frame."""
        # A fading or lost IMU (flag < 1) is left as it is: no prediction, no measurement; its time
        # catches up when it is back (the drift went on while it was away).
        present = imu_flag >= 1.0
        dt = (t - self.t_state) / self.fps * present
        # Predict: o += r dt; P = F P F' + Q with F = [[1, 0, dt], [0, 1, 0], [0, 0, 1]].
        x, P = self.x, self.P
        x[:, 0] += x[:, 2] * dt
        P[:, 0, :] += dt[:, None] * P[:, 2, :]
        P[:, :, 0] += dt[:, None] * P[:, :, 2]
        P[:, 1, 1] += self.q_bias * dt
        P[:, 2, 2] += self.q_rate * dt
        self.t_state[present] = t
        # Gates: fully present, and turning slowly since the last update (the reference lags a fast
        # turn); the angle between two orientations is 2 acos |<q1, q2>|.
        ok = present
        if self.t_prev >= 0:
            cos_half = np.abs((self.raw * self._prev_raw).sum(1))
            ok &= cos_half >= np.cos(0.5 * self.max_turn * (t - self.t_prev) / self.fps)
        np.copyto(self._prev_raw, self.raw)
        self.t_prev = t
        innovation = wrap(relative_heading - self.mean - x[:, 0] - x[:, 1])     # H = [1, 1, 0]
        ph = P[:, :, 0] + P[:, :, 1]                        # P H'
        s = ph[:, 0] + ph[:, 1] + self.r
        ok &= innovation * innovation <= self.gate * self.gate * s
        gain = ph * (ok / s)[:, None]                       # 0 for the IMUs not measured
        x += gain * innovation[:, None]
        P -= gain[:, :, None] * ph[:, None, :]
        # The offset is an angle: kept within +-2 pi however many turns it makes over hours (a 90-minute
        # soak left it at 2,969 deg). 4 pi is its half-angle quaternion's period: the correction never
        # flips sign.
        offset = x[:, 0]
        offset += 2.0 * np.pi
        np.remainder(offset, 4.0 * np.pi, out=offset)
        offset -= 2.0 * np.pi
        self.updates += ok
        self.apply_estimate()
        return True

    def observe_frame(self, t, inputs, s=None, row=None):
        """observe() on a pipeline's frame t, from its inputs (edge.frame.FrameBuffers.inputs: the
        named views of the frame's signals): against the body (body_references: the waist puck, the
        chest halfway to the headset), or against decoder row `row` of ring slot s through
        `decoder_fk(s, row, out)` (FK from the waist without the IMU override), handed to the observer
        when it is made."""
        if t % self.every or not np.count_nonzero(inputs["imu_flag"]):     # not this frame, or no extra IMU worn
            return False
        if self.reference == "pelvis":
            # heading_of(a * b^-1) needs only that product's w and y: a . b and a . (-by, bz, bw, -bx).
            w = inputs["waist_rot"]
            self._waist_y[:] = -w[2], w[3], w[0], -w[1]
            z = 2.0 * np.arctan2(self.raw @ self._waist_y, self.raw @ w)
            z[0] -= 0.5 * wrap(2.0 * np.arctan2(inputs["head_rot"] @ self._waist_y, inputs["head_rot"] @ w))
            return self.observe_heading(t, z, inputs["imu_flag"])
        out = self._fk
        self.decoder_fk(s, row, out)
        return self.observe(t, quat.from_matrix(out[1][0, IMU_JOINTS]), inputs["imu_flag"])

    def correct_frame(self, inputs, sig):
        """correct() on a pipeline's frame (inputs: FrameBuffers.inputs, whose IMU view the compiled core
        reads), and the frame's Signals with those corrected orientations (what the numpy path reads):
        one Signals kept and refilled field by field, no arrays made."""
        if not np.count_nonzero(inputs["imu_flag"]):    # no extra IMU worn: nothing to turn (count_nonzero: a fifth of .any()'s cost)
            return sig
        self.correct(inputs["imu_rot"])
        if self._sig is None:                       # the first frame: the Signals kept (one pipeline's observer)
            self._imu_rot_view, self._sig = inputs["imu_rot"][None], copy.copy(sig)
        out = self._sig
        for name in SIGNAL_FIELDS:
            setattr(out, name, getattr(sig, name))
        out.imu_rot = self._imu_rot_view
        return out
