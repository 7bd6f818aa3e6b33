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
from dataclasses import dataclass

import numpy as np

from edge import quat
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
    """The last few samples of one device (time-sorted, board clock), values as flat float vectors."""

    def __init__(self, width, capacity=32):
        self.t = np.full(capacity, -np.inf)
        self.v = np.zeros((capacity, width))
        self.rx = np.full(capacity, -np.inf)      # when each kept sample reached the board (its clock)
        self.used_rx = -np.inf                    # ... that of the newest sample the last sample() used
        self.clock = ClockOffset()
        self.last_device_t = -np.inf
        self.last_received_t = -np.inf
        self.backwards = 0
        self.forwards = 0             # the device clock leapt ahead of the board's (>JUMP_S more than it)
        self.dropped = 0

    def add(self, device_t, received_t, values):
        if device_t < self.last_device_t - 1.0:       # the device clock jumped back (a reset): start over
            self.clock = ClockOffset()
            self.t[:] = -np.inf
            self.backwards += 1
            self.last_device_t = device_t
        else:
            if device_t - self.last_device_t > received_t - self.last_received_t + JUMP_S:
                self.forwards += 1
            self.last_device_t = max(self.last_device_t, device_t)
        self.last_received_t = received_t
        t = device_t + self.clock.update(device_t, received_t)
        oldest = int(np.argmin(self.t))
        if t <= self.t[oldest] or np.any(self.t == t):
            self.dropped += 1                         # older than anything we keep, or a duplicate
            return
        self.t[oldest] = t
        self.v[oldest] = values
        self.rx[oldest] = received_t

    @property
    def newest(self):
        return float(self.t.max())

    def age(self, t):
        """Seconds since the newest sample at board time t (inf if none)."""
        return t - self.newest if self.newest > -np.inf else np.inf

    def sample(self, t):
        """Interpolated value at board time t: (value, age of the newest sample used) or (None, inf)."""
        # The newest kept time at or before t, and the oldest after it. Empty slots (-inf) and any
        # non-finite time fall out of both: they are neither <= t nor > t with a finite value.
        ts = self.t
        before = np.where(ts <= t, ts, -np.inf)
        after = np.where(ts > t, ts, np.inf)
        i0, i1 = int(before.argmax()), int(after.argmin())
        t0, t1 = float(before[i0]), float(after[i1])
        if t0 == -np.inf:
            if t1 == np.inf:                         # nothing kept
                self.used_rx = -np.inf
                return None, np.inf
            self.used_rx = float(self.rx[i1])
            return self.v[i1].copy(), 0.0            # t is older than everything kept: use the oldest
        if t1 == np.inf:                             # t is past the newest: hold it
            self.used_rx = float(self.rx[i0])
            return self.v[i0].copy(), t - t0
        self.used_rx = float(self.rx[i1])
        w = (t - t0) / (t1 - t0)
        return interpolate(self.v[i0], self.v[i1], w), 0.0


def interpolate(a, b, w):
    """Linear for positions, slerp for the quaternion of a packed [pos3, quat4] vector. Samples a few
    milliseconds apart differ by a few degrees, where normalised lerp equals slerp to ~1e-6 rad."""
    q0, q1 = a[3:7], b[3:7]
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d                             # dot(q0, -q1) is exactly -dot(q0, q1)
    out = a + w * (b - a)
    if d > 0.995:                                   # closer than ~11 degrees
        q = q0 + w * (q1 - q0)
        out[3:7] = q / np.sqrt(np.dot(q, q))
    else:
        out[3:7] = quat.slerp(q0, q1, w)
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
    """

    HANDS = ("l_hand", "r_hand")

    def __init__(self, trackers=("waist",), lost_after=0.25, blend_s=0.5, decay_s=1.0, latency=0.0):
        self.lost_after, self.blend_s, self.decay_s, self.latency = lost_after, blend_s, decay_s, latency
        self.streams = {"head": Stream(7), "l_hand": Stream(7), "r_hand": Stream(7)}
        self.streams.update({name: Stream(7) for name in trackers})    # [pos3 (unused), quat4]
        self.trackers = tuple(trackers)
        self._held = {}                              # source -> (value held when lost, time lost)
        self._recover = {}                           # source -> (value at recovery, time recovered)
        self._last = {}
        self._held_extra = {}                        # what a held source remembers from when it was lost
        self.imu_flag = np.zeros(NUM_IMUS)           # the extra IMUs' presence (edge.imus order), faded per tick
        self._imu_rot = np.tile([1.0, 0.0, 0.0, 0.0], (NUM_IMUS, 1))
        self._imu_t = None
        self.non_finite = 0                          # samples dropped for a NaN or infinity (decoders refuse them first)
        self.unknown_trackers = 0                    # samples of a tracker the config does not name

    def add_headset(self, s, received=None):
        received = s.received if received is None else received
        head = np.concatenate([s.head_pos, s.head_rot])
        if not np.all(np.isfinite(head)):
            self.non_finite += 1
            return
        self.streams["head"].add(s.t, received, head)
        for k, name in enumerate(self.HANDS):
            hand = np.concatenate([s.hand_pos[k], s.hand_rot[k]])
            if s.hand_valid[k] and np.all(np.isfinite(hand)):
                self.streams[name].add(s.t, received, hand)

    def add_tracker(self, s, received=None):
        stream = self.streams.get(s.tracker)
        if stream is None or s.tracker in ("head",) + self.HANDS:
            self.unknown_trackers += 1
            return
        if not np.all(np.isfinite(s.quat)):
            self.non_finite += 1
            return
        stream.add(s.t, s.received if received is None else received, np.concatenate([np.zeros(3), s.quat]))

    def frame(self, t):
        """Signals (T=1) at board time t (minus the configured latency), and the Health of every source."""
        t = t - self.latency
        head, age = self.streams["head"].sample(t)
        if head is None:
            return None, Health({name: True for name in self.streams}, 0, 0)
        lost = {"head": age > self.lost_after}
        head = self._guard("head", head, lost["head"], t)
        hands = []
        for k, name in enumerate(self.HANDS):
            v, age = self.streams[name].sample(t)
            lost[name] = v is None or age > self.lost_after
            if v is None:
                v = np.concatenate([self._neutral_hand(head, k), head[3:7]])
            hands.append(self._guard(name, v, lost[name], t, lambda held, since, k=k: self._decay_hand(held, since, head, k)))
        waist = None
        ages = {}
        step = 0.0 if self._imu_t is None else max(t - self._imu_t, 0.0) / FADE_S
        self._imu_t = t
        for name in self.trackers:
            v, age = self.streams[name].sample(t)
            lost[name] = v is None or age > self.lost_after
            ages[name] = self.streams[name].age(t)
            if name == "waist":
                if v is None:                        # never heard from: upright, facing where the headset faces
                    v = np.concatenate([np.zeros(3), quat.from_yaw(quat.yaw(head[3:7]))])
                waist = self._guard(name, v, lost[name], t, lambda held, since, h=head: self._follow_head(held, h))
            elif name in IMU_INDEX:                  # an extra IMU: hold while lost, fade its flag
                k = IMU_INDEX[name]
                if not lost[name]:
                    self._imu_rot[k] = quat.normalize(v[3:7])
                target = 0.0 if lost[name] else 1.0
                self.imu_flag[k] += float(np.clip(target - self.imu_flag[k], -step, step))
        if waist is None:
            waist = np.concatenate([np.zeros(3), quat.from_yaw(quat.yaw(head[3:7]))])
        sig = Signals(head[None, 0:3], quat.normalize(head[None, 3:7]),
                      np.stack([hands[0][0:3], hands[1][0:3]])[None],
                      quat.normalize(np.stack([hands[0][3:7], hands[1][3:7]]))[None],
                      quat.normalize(waist[None, 3:7]), np.zeros((1, 3)), self._imu_rot[None].copy(), self.imu_flag[None].copy())
        streams = self.streams.values()
        newest_rx = max((s.used_rx for name, s in self.streams.items() if not lost[name]), default=-np.inf)
        return sig, Health(lost, sum(s.dropped for s in streams), sum(s.backwards for s in streams), ages, newest_rx)

    def _follow_head(self, held, head):
        """A lost waist keeps its tilt but turns with the headset, from the heading offset it had when lost."""
        if "waist_head_yaw" not in self._held_extra:
            self._held_extra["waist_head_yaw"] = quat.yaw(head[3:7])
        turn = quat.from_yaw(np.array(quat.yaw(head[3:7]) - self._held_extra["waist_head_yaw"]))
        out = held.copy()
        out[3:7] = quat.mul(turn, held[3:7])
        return out

    def _neutral_hand(self, head, k):
        return head[0:3] + quat.rotate(quat.from_yaw(quat.yaw(head[3:7])), NEUTRAL_HANDS[k])

    def _decay_hand(self, held, since, head, k):
        """A lost controller drifts from where it was lost to the neutral pose beside the body."""
        a = min(since / self.decay_s, 1.0)
        out = held.copy()
        out[0:3] = (1 - a) * held[0:3] + a * self._neutral_hand(head, k)
        return out

    def _guard(self, name, live, is_lost, t, decay=None):
        """Hold (and decay) while lost; cosine-blend back from the shown value after recovery."""
        if is_lost:
            if name not in self._held:
                self._held[name] = (self._last.get(name, live).copy(), t)
            held, since = self._held[name]
            value = decay(held, t - since) if decay else held
            self._last[name] = value
            return value
        if name in self._held:                        # just recovered
            self._recover[name] = (self._last[name].copy(), t)
            del self._held[name]
            self._held_extra.pop(f"{name}_head_yaw", None)
        if name in self._recover:
            start, t0 = self._recover[name]
            a = (t - t0) / self.blend_s
            if a >= 1.0:
                del self._recover[name]
            else:
                live = interpolate(start, live, 0.5 - 0.5 * np.cos(np.pi * a))   # cosine schedule 0 -> 1
        self._last[name] = live
        return live
