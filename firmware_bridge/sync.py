"""Align sources running at their own rates and clocks to the 60 Hz model clock.

Every device stamps samples with its own clock. Per device we estimate the offset to the board's
clock with a minimum-delay filter (transport delay is never negative, so the smallest
`received - device_time` over a recent window is the offset plus the smallest delay), then keep
each stream's recent samples in time order and interpolate them at the model tick: linear for
positions, slerp for rotations. Late and out-of-order samples are inserted where they belong;
samples older than what we keep are dropped and counted.

A stream that has said nothing for `lost_after` seconds is lost: its last value is held (the
controllers drift to a neutral pose beside the body, expressed in the headset's heading frame so
they follow the user), and when it comes back the output blends from the held value to the live
one over a cosine schedule (RPM's bounded correction) instead of snapping.

The extra body IMUs (edge.imus: chest, thighs, shins, feet) reach the model as orientations and a
presence flag: a lost one holds its last orientation while its flag fades to 0 over edge.imus.FADE_S,
and a returning one is used at once while its flag climbs back, the same fade training saw
(edge.imus.fade), so the model moves between sensor sets smoothly.
"""
import bisect
import math
from dataclasses import dataclass

import numpy as np

from edge.imus import FADE_S, IMU_INDEX, NUM_IMUS
from edge.signals import Signals

# Where lost controllers settle, in the headset's heading frame (hands hanging beside the hips).
NEUTRAL_HANDS = np.array([[0.22, -0.75, 0.05], [-0.22, -0.75, 0.05]])


JUMP_S = 0.25                   # a device clock step this much larger than the board's is a jump, counted


class ClockOffset:
    """Board-minus-device clock offset from a minimum-delay filter over a sliding window of samples."""

    def __init__(self, window=200):
        self.window = np.full(window, np.inf)
        self.n = 0
        self._min = np.inf          # the window's minimum, kept as values come and go

    def update(self, device_t, received_t):
        k = self.n % len(self.window)
        leaving, arriving = self.window[k], received_t - device_t
        self.window[k] = arriving
        self.n += 1
        if arriving <= self._min:
            self._min = arriving
        elif leaving == self._min or arriving != arriving or self._min != self._min:
            self._min = float(self.window.min())    # the minimum left, or a NaN came or is there: look again
        return self.offset

    @property
    def offset(self):
        return float(self._min) if self.n else 0.0


class Stream:
    """The last few samples of one device (board clock), in time order; values as flat float rows.

    Times and values are Python floats in preallocated lists, kept sorted by time (an insert is a
    bisect and a short memmove): a tick's lookups and interpolation are a few dozen float operations,
    where numpy would spend a microsecond a call on 7-element arrays and allocate its temporaries."""

    def __init__(self, width, capacity=32):
        self.capacity = capacity
        self.t = []                               # kept times, ascending (at most `capacity`)
        self.rows = []                            # their rows, in the same order (recycled, never remade)
        self.rx = []                              # when each reached the board (its clock)
        self._spare = [[0.0] * width for _ in range(capacity)]   # rows not in use
        self.used_rx = -math.inf                  # when the newest sample the last sample() used arrived
        self.clock = ClockOffset()
        self.last_device_t = -math.inf
        self.last_received_t = -math.inf
        self.backwards = 0
        self.forwards = 0             # the device clock leapt ahead of the board's (>JUMP_S more than it)
        self.dropped = 0

    @property
    def newest(self):
        return self.t[-1] if self.t else -math.inf

    def add(self, device_t, received_t, values):
        """One sample: its device time, when it reached the board, and `width` values (a sequence)."""
        if device_t < self.last_device_t - 1.0:       # the device clock jumped back (a reset): start over
            self.clock = ClockOffset()
            self._spare += self.rows
            self.t.clear()
            self.rows.clear()
            self.rx.clear()
            self.backwards += 1
            self.last_device_t = device_t
        else:
            if device_t - self.last_device_t > received_t - self.last_received_t + JUMP_S:
                self.forwards += 1
            self.last_device_t = max(self.last_device_t, device_t)
        self.last_received_t = received_t
        t = device_t + self.clock.update(device_t, received_t)
        ts = self.t
        k = bisect.bisect_left(ts, t)
        full = len(ts) == self.capacity
        if not t > -math.inf or (full and k == 0) or (k < len(ts) and ts[k] == t):
            self.dropped += 1                         # older than anything we keep, a duplicate, or NaN
            return
        if full:                                      # make room: the oldest goes
            del ts[0]
            self._spare.append(self.rows.pop(0))
            del self.rx[0]
            k -= 1
        row = self._spare.pop()
        row[:] = values
        ts.insert(k, t)
        self.rows.insert(k, row)
        self.rx.insert(k, received_t)

    def age(self, t):
        """Seconds since the newest sample at board time t (inf if none)."""
        return t - self.t[-1] if self.t else math.inf

    def sample(self, t, out):
        """The value at board time t, interpolated into `out` (a list of `width` floats): the age of the
        newest sample used, or inf (out untouched) when there is none."""
        ts = self.t
        if not ts:                                   # nothing kept
            self.used_rx = -math.inf
            return math.inf
        k = bisect.bisect_right(ts, t)               # ts[k - 1] <= t < ts[k]
        if k == 0:                                   # t is older than everything kept: use the oldest
            self.used_rx = self.rx[0]
            out[:] = self.rows[0]
            return 0.0
        if k == len(ts):                             # t is past the newest: hold it
            self.used_rx = self.rx[-1]
            out[:] = self.rows[-1]
            return t - ts[-1]
        self.used_rx = self.rx[k]
        t0, t1 = ts[k - 1], ts[k]
        interpolate(self.rows[k - 1], self.rows[k], (t - t0) / (t1 - t0), out)
        return 0.0


def interpolate(a, b, w, out):
    """out = a packed [pos3, quat4] row between a and b at w: linear for the position, slerp for the
    quaternion. Samples a few milliseconds apart differ by a few degrees, where normalised lerp equals
    slerp to ~1e-6 rad. Written out scalar by scalar: this runs four times a tick."""
    out[0] = a[0] + w * (b[0] - a[0])
    out[1] = a[1] + w * (b[1] - a[1])
    out[2] = a[2] + w * (b[2] - a[2])
    aw, ax, ay, az = a[3], a[4], a[5], a[6]
    bw, bx, by, bz = b[3], b[4], b[5], b[6]
    d = aw * bw + ax * bx + ay * by + az * bz
    if d < 0:
        bw, bx, by, bz, d = -bw, -bx, -by, -bz, -d
    if d > 0.995:                                   # closer than ~11 degrees
        wa, wb = 1.0 - w, w
    else:
        theta = math.acos(min(d, 1.0))
        s = math.sin(theta)
        wa, wb = math.sin((1.0 - w) * theta) / s, math.sin(w * theta) / s
    qw, qx, qy, qz = wa * aw + wb * bw, wa * ax + wb * bx, wa * ay + wb * by, wa * az + wb * bz
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    out[3], out[4], out[5], out[6] = qw / n, qx / n, qy / n, qz / n
    return out


@dataclass
class Health:
    """Which sources are lost at this tick, and how many samples were dropped for being late."""
    lost: dict
    dropped: int
    backwards: int
    ages: dict = None       # tracker name -> seconds since its newest sample (inf: never heard)
    newest_rx: float = -np.inf  # when the newest sample this frame used reached the board (a live source's)


class FrameSynchronizer:
    """Collects samples from all sources and produces one Signals frame per model tick.

    Sources: the headset's head and its two controllers (each lost on its own: a controller that
    leaves the cameras' view is flagged invalid by the headset) and the IMU trackers by name.

    A tick's work is scalar: every source is one 7-float row ([pos3, quat4]; an IMU's position is
    unused) in preallocated lists, and frame(t, out) writes the Signals and Health it is given, so the
    board's tick allocates no arrays here (tests/test_tick.py counts).
    """

    HANDS = ("l_hand", "r_hand")

    def __init__(self, trackers=("waist",), lost_after=0.25, blend_s=0.5, decay_s=1.0, latency=0.0):
        self.lost_after, self.blend_s, self.decay_s, self.latency = lost_after, blend_s, decay_s, latency
        self.streams = {"head": Stream(7), "l_hand": Stream(7), "r_hand": Stream(7)}
        self.streams.update({name: Stream(7) for name in trackers})    # [pos3 (unused), quat4]
        self.trackers = tuple(trackers)
        self._rows = {name: [0.0] * 7 for name in self.streams}        # each source's value at this tick
        self._held = {}                              # source -> (value held when lost, time lost)
        self._recover = {}                           # source -> (value at recovery, time recovered)
        self._last = {}
        self._held_extra = {}                        # what a held source remembers from when it was lost
        self._scratch = [0.0] * 7
        self._in = [0.0] * 7                         # a sample's row on its way into a stream
        self.imu_flag = np.zeros(NUM_IMUS)           # the extra IMUs' presence (edge.imus order), faded per tick
        self._imu_rot = np.tile([1.0, 0.0, 0.0, 0.0], (NUM_IMUS, 1))
        self._imu_t = None
        self.non_finite = 0                          # samples dropped for a NaN or infinity (decoders refuse them first)
        self.unknown_trackers = 0                    # samples of a tracker the config does not name

    def new_frame(self):
        """A (Signals, Health) pair for frame(t, out=...) to fill every tick."""
        sig = Signals(np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 2, 3)), np.zeros((1, 2, 4)), np.zeros((1, 4)),
                      np.zeros((1, 3)), np.zeros((1, NUM_IMUS, 4)), np.zeros((1, NUM_IMUS)))
        return sig, Health({name: True for name in self.streams}, 0, 0, {name: math.inf for name in self.trackers})

    def add_headset(self, s, received=None):
        received = s.received if received is None else received
        row = self._in
        row[0:3], row[3:7] = s.head_pos.tolist(), s.head_rot.tolist()
        if not all(map(math.isfinite, row)):
            self.non_finite += 1
            return
        self.streams["head"].add(s.t, received, row)
        for k, name in enumerate(self.HANDS):
            row[0:3], row[3:7] = s.hand_pos[k].tolist(), s.hand_rot[k].tolist()
            if s.hand_valid[k] and all(map(math.isfinite, row)):
                self.streams[name].add(s.t, received, row)

    def add_tracker(self, s, received=None):
        stream = self.streams.get(s.tracker)
        if stream is None or s.tracker in ("head",) + self.HANDS:
            self.unknown_trackers += 1
            return
        row = self._in
        row[0:3], row[3:7] = (0.0, 0.0, 0.0), s.quat.tolist()
        if not all(map(math.isfinite, row)):
            self.non_finite += 1
            return
        stream.add(s.t, s.received if received is None else received, row)

    def frame(self, t, out=None):
        """Signals (T=1) at board time t (minus the configured latency), and the Health of every source:
        into `out` (a new_frame() pair, reused tick after tick) when given, else new objects."""
        t = t - self.latency
        rows, streams = self._rows, self.streams
        sig, health = out if out is not None else self.new_frame()
        lost = health.lost
        head = rows["head"]
        age = streams["head"].sample(t, head)
        if age == math.inf:
            for name in lost:
                lost[name] = True
            health.dropped = health.backwards = 0
            health.newest_rx = -math.inf
            return None, health
        lost["head"] = age > self.lost_after
        self._guard("head", head, lost["head"], t)
        for k, name in enumerate(self.HANDS):
            hand = rows[name]
            age = streams[name].sample(t, hand)
            lost[name] = age > self.lost_after
            if age == math.inf:
                self._neutral_hand(head, k, hand)
                hand[3:7] = head[3:7]
            self._guard(name, hand, lost[name], t)
        self._trackers(t, head, lost, health.ages)
        self._write(sig, head, rows)
        dropped = backwards = 0
        newest_rx = -math.inf
        for name, s in streams.items():
            dropped += s.dropped
            backwards += s.backwards
            if not lost[name] and s.used_rx > newest_rx:
                newest_rx = s.used_rx
        health.dropped, health.backwards, health.newest_rx = dropped, backwards, newest_rx
        return sig, health

    def _trackers(self, t, head, lost, ages):
        """The waist and the extra IMUs at t: the waist held and turned with the headset while lost, an
        extra IMU held while its presence flag fades."""
        step = 0.0 if self._imu_t is None else max(t - self._imu_t, 0.0) / FADE_S
        self._imu_t = t
        waist = self._rows.get("waist")
        for name in self.trackers:
            row, stream = self._rows[name], self.streams[name]
            age = stream.sample(t, row)
            lost[name] = age > self.lost_after
            ages[name] = stream.age(t)
            if name == "waist":
                if age == math.inf:                  # never heard from: upright, facing where the headset faces
                    row[0:3] = (0.0, 0.0, 0.0)
                    yaw_quat(head_yaw(head), row)
                self._guard(name, row, lost[name], t)
            elif name in IMU_INDEX:                  # an extra IMU: hold while lost, fade its flag
                k = IMU_INDEX[name]
                if not lost[name]:
                    n = max(math.sqrt(row[3] * row[3] + row[4] * row[4] + row[5] * row[5] + row[6] * row[6]), 1e-8)
                    for c in range(4):
                        self._imu_rot[k, c] = row[3 + c] / n
                target = 0.0 if lost[name] else 1.0
                self.imu_flag[k] += min(max(target - self.imu_flag[k], -step), step)
        if waist is None:                            # no waist configured: upright under the headset
            waist = self._scratch
            yaw_quat(head_yaw(head), waist)
        self._waist = waist

    def _write(self, sig, head, rows):
        """The tick's rows into the Signals arrays (quaternions normalised)."""
        hp, hr, cp, cr, wr = sig.head_pos[0], sig.head_rot[0], sig.hand_pos[0], sig.hand_rot[0], sig.waist_rot[0]
        hp[0], hp[1], hp[2] = head[0], head[1], head[2]
        put_unit(hr, head)
        for k, name in enumerate(self.HANDS):
            hand = rows[name]
            cp[k, 0], cp[k, 1], cp[k, 2] = hand[0], hand[1], hand[2]
            put_unit(cr[k], hand)
        put_unit(wr, self._waist)
        sig.imu_rot[0] = self._imu_rot
        sig.imu_flag[0] = self.imu_flag

    def _neutral_hand(self, head, k, out):
        """Where a lost controller settles: beside the hips, in the headset's heading frame (into out[0:3])."""
        yaw = head_yaw(head)
        c, s = math.cos(yaw), math.sin(yaw)
        x, y, z = NEUTRAL_HANDS[k]
        out[0], out[1], out[2] = head[0] + c * x + s * z, head[1] + y, head[2] - s * x + c * z
        return out

    def _hold(self, name, held, row, since):
        """What a lost source shows, from the value it was lost with: a controller drifts to the neutral
        pose beside the body, the waist keeps its tilt but turns with the headset."""
        row[:] = held
        if name in self.HANDS:
            a = min(since / self.decay_s, 1.0)
            k = self.HANDS.index(name)
            target = self._neutral_hand(self._rows["head"], k, self._scratch)
            for c in range(3):
                row[c] = (1 - a) * held[c] + a * target[c]
        elif name == "waist":
            head = self._rows["head"]
            if "waist_head_yaw" not in self._held_extra:
                self._held_extra["waist_head_yaw"] = head_yaw(head)
            turn = yaw_quat(head_yaw(head) - self._held_extra["waist_head_yaw"], self._scratch)
            quat_mul_into(turn[3:7], held[3:7], row)

    def _guard(self, name, live, is_lost, t):
        """Hold (and decay) while lost; cosine-blend back from the shown value after recovery (in place)."""
        last = self._last.get(name)
        if is_lost:
            if name not in self._held:
                self._held[name] = (list(live if last is None else last), t)
            held, since = self._held[name]
            self._hold(name, held, live, t - since)
            self._remember(name, live)
            return
        if name in self._held:                        # just recovered
            self._recover[name] = (list(self._last[name]), t)
            del self._held[name]
            self._held_extra.pop(f"{name}_head_yaw", None)
        if name in self._recover:
            start, t0 = self._recover[name]
            a = (t - t0) / self.blend_s
            if a >= 1.0:
                del self._recover[name]
            else:
                interpolate(start, list(live), 0.5 - 0.5 * math.cos(math.pi * a), live)   # cosine schedule 0 -> 1
        self._remember(name, live)

    def _remember(self, name, row):
        last = self._last.get(name)
        if last is None:
            self._last[name] = list(row)
        else:
            last[:] = row


def head_yaw(row):
    """edge.quat.yaw of a row's quaternion (row[3:7]): the heading of its forward axis (+Z) about +Y."""
    w, x, y, z = row[3], row[4], row[5], row[6]
    # +Z rotated by (w, x, y, z): its x and z components
    fx = 2.0 * (x * z + w * y)
    fz = 1.0 - 2.0 * (x * x + y * y)
    return math.atan2(fx, fz)


def yaw_quat(theta, out):
    """edge.quat.from_yaw(theta) into out[3:7]."""
    out[3], out[4], out[5], out[6] = math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0
    return out


def quat_mul_into(a, b, out):
    """edge.quat.mul(a, b) into out[3:7]."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    out[3] = aw * bw - ax * bx - ay * by - az * bz
    out[4] = aw * bx + ax * bw + ay * bz - az * by
    out[5] = aw * by - ax * bz + ay * bw + az * bx
    out[6] = aw * bz + ax * by - ay * bx + az * bw
    return out


def put_unit(dst, row):
    """row[3:7] normalised (edge.quat.normalize) into dst[0:4]."""
    n = max(math.sqrt(row[3] * row[3] + row[4] * row[4] + row[5] * row[5] + row[6] * row[6]), 1e-8)
    dst[0], dst[1], dst[2], dst[3] = row[3] / n, row[4] / n, row[5] / n, row[6] / n
