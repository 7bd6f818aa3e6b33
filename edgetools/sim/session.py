"""A session: what every transport carried, timestamped, plus ground truth when it came from mocap.

- serial links (`headset`, `hub`): the exact bytes of each frame and when it was sent;
- `can`: each CAN frame (id, data) and when it was sent;
- `i2c`: the BNO055's output registers over time (quaternion, linear acceleration), which the
  register-level fake serves to the driver.

`synthesize` builds one from a Take (mocap through the same signal code as training) with each device
at its own rate, clock offset, drift and jitter, and with generation-time faults applied.
`save`/`load` keep it in one .npz (a few hundred KB for 15 s).
"""
import json
from dataclasses import dataclass, field

import numpy as np

from edge.shutdown import replace_whole

from edge import quat
from edge.imus import IMU_LOCATIONS, ImuNoise
from edge.signals import Signals
from motion.synth import DeviceNoise
from motion.takes import Take
from firmware_bridge.wire import messages
from firmware_bridge.samples import HeadsetSample, TrackerSample
from firmware_bridge.wire.can_frames import encode_node_frames

# Who sits where: the waist puck on I2C, the feet on CAN, every other extra IMU (edge.imus) on the
# serial hub. With fewer transports the waist moves to the hub, then to CAN node 3, and the extra IMUs
# to whichever of hub and CAN there is.
CAN_NODES = {1: "l_foot", 2: "r_foot", 3: "waist", 4: "chest", 5: "l_thigh", 6: "r_thigh", 7: "l_shin", 8: "r_shin"}
HUB_IDS = {0: "chest", 1: "waist", 2: "l_thigh", 3: "r_thigh", 4: "l_shin", 5: "r_shin", 6: "l_foot", 7: "r_foot"}
# The extra IMUs a replay wears unless told: the two CAN foot trackers (the demo shows them in use).
DEFAULT_TRACKERS = ("l_foot", "r_foot")


def placement(transports, trackers=None):
    """transport -> the tracker names it carries, for the waist and the extra IMUs `trackers` (None: the
    CAN foot trackers when there is a bus for them)."""
    if trackers is None:
        trackers = DEFAULT_TRACKERS if {"serial", "can"} & set(transports) else ()
    place = {"i2c": [], "hub": [], "can": [], "slimevr": []}
    if "slimevr" in transports:         # SlimeVR trackers over Wi-Fi: the waist and every extra IMU
        place["slimevr"] = ["waist", *trackers]
        return place
    waist_on = "i2c" if "i2c" in transports else "hub" if "serial" in transports else "can"
    place[waist_on].append("waist")
    for name in trackers:
        feet_on_can = name in ("l_foot", "r_foot") and "can" in transports
        place["can" if feet_on_can or "serial" not in transports else "hub"].append(name)
    if not {"serial", "can"} & set(transports) and trackers:
        raise ValueError(f"extra trackers {', '.join(trackers)} need the serial hub or CAN (--transport)")
    return place
RATES = {"headset": 72.0, "hub": 100.0, "can": 100.0, "i2c": 100.0, "slimevr": 100.0}
# The simulated SlimeVR trackers' MACs, one tracker (sensor 0) per body location.
SLIMEVR_MACS = {name: f"02:ed:9e:00:00:{k + 1:02x}" for k, name in enumerate(("waist",) + IMU_LOCATIONS)}


@dataclass
class SerialLog:
    t: list = field(default_factory=list)        # send time (s, true session time)
    frames: list = field(default_factory=list)   # bytes of each frame as sent

    def add(self, t, data):
        self.t.append(t)
        self.frames.append(bytes(data))


@dataclass
class Session:
    name: str
    fps: float
    duration: float
    transports: tuple
    headset: SerialLog
    hub: SerialLog
    can_t: np.ndarray
    can_id: np.ndarray
    can_data: np.ndarray                          # [K,8]
    i2c_t: np.ndarray
    i2c_quat: np.ndarray
    i2c_accel: np.ndarray
    gt_pos: np.ndarray = None                     # [T,J,3] at fps, when known
    meta: dict = field(default_factory=dict)
    slimevr: dict = field(default_factory=dict)   # SlimeVR tracker MAC -> SerialLog of its datagrams (after its handshake)

    def save(self, path):
        def pack(log):
            lengths = np.array([len(f) for f in log.frames], np.int64)
            data = np.frombuffer(b"".join(log.frames), np.uint8) if log.frames else np.zeros(0, np.uint8)
            return np.array(log.t, np.float64), lengths, data
        ht, hl, hd = pack(self.headset)
        bt, bl, bd = pack(self.hub)
        extra = {} if self.gt_pos is None else {"gt_pos": self.gt_pos.astype(np.float32)}
        for i, log in enumerate(self.slimevr.values()):
            extra.update(zip((f"slimevr{i}_t", f"slimevr{i}_len", f"slimevr{i}_bytes"), pack(log), strict=True))
        slimevr_macs = list(self.slimevr)
        path = str(path) if str(path).endswith(".npz") else f"{path}.npz"      # as numpy names it
        with replace_whole(path) as tmp, open(tmp, "wb") as f:      # the old file or the new one, never half
            self._savez(f, ht, hl, hd, bt, bl, bd, slimevr_macs, extra)

    def _savez(self, f, ht, hl, hd, bt, bl, bd, slimevr_macs, extra):
        np.savez_compressed(f, kind="edgepose-session", version=1, meta=json.dumps(
            {"name": self.name, "fps": self.fps, "duration": self.duration, "transports": list(self.transports),
             "slimevr_macs": slimevr_macs, **self.meta}), headset_t=ht, headset_len=hl, headset_bytes=hd, hub_t=bt, hub_len=bl, hub_bytes=bd,
            can_t=self.can_t, can_id=self.can_id, can_data=self.can_data, i2c_t=self.i2c_t,
            i2c_quat=self.i2c_quat.astype(np.float32), i2c_accel=self.i2c_accel.astype(np.float32), **extra)

    @classmethod
    def load(cls, path):
        d = np.load(path, allow_pickle=False)
        if "kind" not in d.files or str(d["kind"]) != "edgepose-session":
            raise ValueError(f"{path}: not an edgepose session recording")
        meta = json.loads(str(d["meta"]))

        def unpack(prefix):
            ends = np.cumsum(d[f"{prefix}_len"])
            data = d[f"{prefix}_bytes"].tobytes()
            starts = ends - d[f"{prefix}_len"]
            return SerialLog(list(d[f"{prefix}_t"]), [data[a:b] for a, b in zip(starts, ends, strict=True)])
        slimevr = {mac: unpack(f"slimevr{i}") for i, mac in enumerate(meta.pop("slimevr_macs", []))}
        return cls(meta.pop("name"), meta.pop("fps"), meta.pop("duration"), tuple(meta.pop("transports")),
                   unpack("headset"), unpack("hub"), d["can_t"], d["can_id"], d["can_data"], d["i2c_t"],
                   d["i2c_quat"].astype(np.float64), d["i2c_accel"].astype(np.float64),
                   d["gt_pos"].astype(np.float64) if "gt_pos" in d.files else None, meta, slimevr)

    def digest(self):
        """sha256 over every byte each transport carried, in order."""
        import hashlib
        h = hashlib.sha256()
        for log in (self.headset, self.hub, *self.slimevr.values()):
            for t, f in zip(log.t, log.frames, strict=True):
                h.update(np.float64(t).tobytes() + f)
        for arr in (self.can_t, self.can_id, self.can_data, self.i2c_t, self.i2c_quat.astype(np.float32),
                    self.i2c_accel.astype(np.float32)):
            h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()


# ----------------------------------------------------------------------------- device clocks

@dataclass
class DeviceClock:
    """A device's own clock: t_device = t_true * (1 + drift) + offset; sends jitter around its rate."""
    offset: float
    drift: float
    jitter: float

    def stamp(self, t):
        return t * (1.0 + self.drift) + self.offset


def emission_times(rate, duration, jitter, rng):
    t = np.arange(0.0, duration, 1.0 / rate)
    return np.clip(t + rng.normal(0, jitter, len(t)), 0.0, duration)


def signal_at(sig: Signals, fps, t):
    """Signals interpolated at true time t (lerp positions, slerp rotations)."""
    x = np.clip(t * fps, 0, sig.frames - 1)
    i0 = int(np.floor(x))
    i1 = min(i0 + 1, sig.frames - 1)
    w = x - i0
    lerp = lambda a: a[i0] * (1 - w) + a[i1] * w
    return (lerp(sig.head_pos), quat.slerp(sig.head_rot[i0], sig.head_rot[i1], w), lerp(sig.hand_pos),
            quat.slerp(sig.hand_rot[i0], sig.hand_rot[i1], np.full(2, w)), quat.slerp(sig.waist_rot[i0], sig.waist_rot[i1], w),
            lerp(sig.waist_acc))


def imu_at(take, name, t, imus=None):
    """A tracker's orientation at true time t: the waist puck's signal, or an extra IMU's (from `imus`,
    the noisy orientations, when given)."""
    q = take.signals.waist_rot if name == "waist" else (imus or take.imu)[name]
    x = np.clip(t * take.fps, 0, len(q) - 1)
    i0 = int(np.floor(x))
    return quat.slerp(q[i0], q[min(i0 + 1, len(q) - 1)], x - i0)


# ----------------------------------------------------------------------------- faults

FAULTS = {
    "noise": {"noise": True},
    "loss": {"loss": 0.02},
    "corrupt": {"ber": 1e-4},
    # DragPoser: each frame one worn extra IMU drops w.p. 1 %, back after 100 frames (as edge eval --faults)
    "disconnect": {"disconnect": 0.01, "disconnect_frames": 100},
    # the same with the waist puck among the trackers that drop (the 4-point input itself goes)
    "disconnect-waist": {"disconnect": 0.01, "disconnect_frames": 100, "disconnect_waist": True},
    "hand-loss": {"hand_loss": 0.025, "hand_gap_s": [0.5, 2.0]},    # RPM: 2.5% per frame per hand, 0.5-2 s
    "unplug": {"unplug_at": 2.0, "unplug_s": 0.5},
    "i2c-errors": {"i2c_error_rate": 0.05},
    "slow-i2c": {"i2c_block_ms": 50, "i2c_block_every_ms": 200},    # a read that blocks 50 ms every 200 ms
    "can-busoff": {"busoff_at": 2.0, "busoff_s": 1.0},
    "clock-jump": {"clock_jump_at": 2.0, "clock_jump_s": 0.75},
    "unplug-foot": {"tracker_unplug": "l_foot", "tracker_unplug_at": 4.0},  # an extra IMU goes silent for good
    # the last SlimeVR tracker goes silent for 2 s, then restarts (a new handshake)
    "slimevr-restart": {"tracker_unplug": "slimevr", "tracker_unplug_at": 4.0, "tracker_unplug_s": 2.0},
    "slimevr-flood": {"slimevr_flood_pps": 10000},   # a device sending 10,000 garbage datagrams a second
}


def fault_profile(spec):
    """'clean', a profile name, several joined by '+', or a JSON object of fault parameters."""
    if not spec or spec == "clean":
        return {}
    if spec.strip().startswith("{"):
        try:
            params = json.loads(spec)
        except ValueError as e:
            raise ValueError(f"--faults JSON is not valid: {e}") from None
        known = {k for p in FAULTS.values() for k in p}
        unknown = set(params) - known
        if unknown:
            raise ValueError(f"unknown fault parameter {sorted(unknown)[0]!r}; known: {', '.join(sorted(known))}")
        return params
    out = {}
    for name in spec.split("+"):
        if name not in FAULTS:
            raise ValueError(f"unknown fault profile {name!r}; profiles: {', '.join(FAULTS)} (or a JSON object)")
        out.update(FAULTS[name])
    return out


def gaps(rng, frames, start_p, length_frames):
    """Boolean [frames] mask of outage windows: each frame starts one with probability start_p."""
    out = np.zeros(frames, bool)
    t = 0
    while t < frames:
        if rng.random() < start_p:
            n = int(length_frames(rng))
            out[t:t + n] = True
            t += n
        t += 1
    return out


def flip_bits(data, ber, rng):
    """Flip each bit with probability ber (the 0x00 delimiters included: a real line hits those too)."""
    if ber <= 0 or not data:
        return data
    bits = len(data) * 8
    n = rng.binomial(bits, ber)
    if n == 0:
        return data
    b = bytearray(data)
    for pos in rng.choice(bits, n, replace=False):
        b[pos // 8] ^= 1 << (pos % 8)
    return bytes(b)


# ----------------------------------------------------------------------------- synthesis

def synthesize(take: Take, transports=("serial", "i2c", "can"), faults=None, seed=0, seconds=None,
               trackers=None, *, place=None, start=0.0, clocks=None):
    """Device traffic for a take. The headset always speaks serial; IMUs go where `placement` puts them
    (or where `place`, a placement dict, says). The extra IMUs `trackers` carry IMU noise
    (edge.imus.ImuNoise), as `edge eval` and training have it. One seeded generator draws everything, in
    a fixed order: the same arguments make the same bytes.
    A soak plays one session after another into one board: `start` (s) puts this one's traffic after
    the last one's, on the same device clocks (`clocks`, a meta["clocks"] dict) with the frame counters
    and SlimeVR packet numbers running on, as the devices' own would."""
    faults = faults or {}
    rng = np.random.default_rng(seed)
    place = place or placement(transports, trackers)
    trackers = tuple(n for n in place["hub"] + place["can"] + place["slimevr"] if n != "waist")
    missing = [n for n in trackers if n not in (take.imu or {})]
    if missing:
        raise ValueError(f"{take.name} carries no orientation for {', '.join(missing)} (an older sample file: "
                         f"replay the BVH clip, or rebuild the sample with python -m edgetools.make_sample)")
    tx = _Traffic(take, place, faults, rng, _noisy_imus(take, trackers, seed), seconds, start, clocks)
    tx.plan_faults(trackers)
    headset, hub = tx.headset_log(), tx.hub_log()
    can_t, can_id, can_data = tx.can_frames()
    slimevr = tx.slimevr_logs()
    i2c_t, i2c_q, i2c_a = tx.i2c_samples("i2c" in transports)
    duration = tx.duration
    gt = None if take.gt_pos is None else take.gt_pos[:int(round(duration * tx.fps))]
    meta = {"faults": faults, "seed": seed, "placement": place, "start": start, "trackers": ["waist", *trackers],
            "clocks": {k: {"offset": c.offset, "drift": c.drift} for k, c in tx.clocks.items()},
            "source": take.name, "slimevr_trackers": {SLIMEVR_MACS[n]: n for n in place["slimevr"]}}
    return Session(take.name, tx.fps, duration, tuple(transports), headset, hub, np.array(can_t),
                   np.array(can_id, np.int64), np.array(can_data, np.uint8).reshape(-1, 8), i2c_t, i2c_q, i2c_a,
                   gt, meta, slimevr)


def _noisy_imus(take, trackers, seed):
    """The extra IMUs' orientations with ImuNoise, from a generator of their own ({name: [T,4]})."""
    if not trackers:
        return {}
    noisy = ImuNoise().apply(np.stack([take.imu[n] for n in trackers], axis=1), take.fps, np.random.default_rng([seed, 13]))
    return {n: noisy[:, k] for k, n in enumerate(trackers)}


class _Traffic:
    """One take's traffic being made: the signals, the device clocks, the fault plan and the generator,
    shared by each device's log below (called in synthesize's order, which fixes the random draws)."""

    def __init__(self, take, place, faults, rng, imus, seconds, start=0.0, clocks=None):
        self.take, self.place, self.faults, self.rng, self.imus = take, place, faults, rng, imus
        self.start = start          # session time of this traffic's t = 0 (a soak's later part)
        self.fps = fps = take.fps
        self.duration = take.frames / fps if seconds is None else min(seconds, take.frames / fps)
        self.sig = DeviceNoise().apply(take.signals, fps, rng) if faults.get("noise") else take.signals
        self.clocks = {name: DeviceClock(rng.uniform(-50, 50), rng.normal(0, 50e-6), 0.0005) for name in RATES}
        for name, c in (clocks or {}).items():          # drawn above all the same: the same stream follows
            self.clocks[name] = DeviceClock(c["offset"], c["drift"], 0.0005)
        if "clock_jump_at" in faults:
            self.clocks["headset"].jump = (faults["clock_jump_at"], faults["clock_jump_s"])
        self.frames60 = int(np.ceil(self.duration * fps)) + 1
        self.loss, self.ber = faults.get("loss", 0.0), faults.get("ber", 0.0)

    def plan_faults(self, trackers):
        """Which tracker is silent on which frame, and when each hand is lost."""
        faults, rng, n60, fps = self.faults, self.rng, self.frames60, self.fps
        self.dropped = {tracker: np.zeros(n60, bool) for tracker in ("waist",) + IMU_LOCATIONS}
        if "disconnect" in faults:      # DragPoser's protocol: each frame one worn IMU drops w.p. p, back after n frames
            worn = ["waist", *trackers] if faults.get("disconnect_waist") else list(trackers)
            n = int(faults.get("disconnect_frames", 100))
            for f in np.flatnonzero(rng.random(n60) < faults["disconnect"]):
                pick = rng.integers(max(len(worn), 1))     # drawn even with none worn: the same take's stream
                if worn:
                    self.dropped[worn[pick]][f:f + n] = True
        if faults.get("tracker_unplug") in self.dropped:
            self.dropped[faults["tracker_unplug"]][int(faults["tracker_unplug_at"] * fps):] = True
        self.hands_gone = [gaps(rng, n60, faults["hand_loss"], lambda r: r.uniform(*faults.get("hand_gap_s", [0.5, 2.0])) * fps)
                           if "hand_loss" in faults else np.zeros(n60, bool) for _ in range(2)]

    def device_time(self, name, t):
        c = self.clocks[name]
        jump = getattr(c, "jump", None)
        return c.stamp(self.start + t) + (jump[1] if jump and t >= jump[0] else 0.0)

    def count(self, device, k):
        """The k-th message's counter as the device's own, running on from the parts before."""
        return k + int(round(self.start * RATES[device]))

    def emissions(self, device, clock=None):
        """(k, t, frame) of each message `device` sends at its rate, with its clock's jitter."""
        jitter = self.clocks[clock or device].jitter
        for k, t in enumerate(emission_times(RATES[device], self.duration, jitter, self.rng)):
            yield k, t, min(int(t * self.fps), self.frames60 - 1)

    def has(self, name):
        return name == "waist" or name in self.imus

    def headset_log(self):
        log, rng = SerialLog(), self.rng
        for k, t, f in self.emissions("headset"):
            hp, hr, cp, cr, _, _ = signal_at(self.sig, self.fps, t)
            valid = np.array([not self.hands_gone[0][f], not self.hands_gone[1][f]])
            data = messages.encode_headset_pose(HeadsetSample(self.device_time("headset", t), hp, hr, cp, cr, valid),
                                                self.count("headset", k) & 0xFFFF)
            if rng.random() >= self.loss:
                log.add(self.start + t, flip_bits(data, self.ber, rng))
        return log

    def hub_log(self):
        log, rng, names = SerialLog(), self.rng, self.place["hub"]
        if not names:
            return log
        for k, t, f in self.emissions("hub"):
            samples = [TrackerSample(n, self.device_time("hub", t), imu_at(self.take, n, t, self.imus)) for n in names
                       if self.has(n) and not self.dropped[n][f]]
            if samples and rng.random() >= self.loss:
                log.add(self.start + t, flip_bits(messages.encode_tracker_samples(samples, self.count("hub", k) & 0xFFFF,
                                                                                  HUB_IDS), self.ber, rng))
        return log

    def can_frames(self):
        can_t, can_id, can_data = [], [], []
        if not self.place["can"]:
            return can_t, can_id, can_data
        rng, faults = self.rng, self.faults
        busoff = (faults.get("busoff_at", np.inf), faults.get("busoff_at", np.inf) + faults.get("busoff_s", 0))
        for k, t, f in self.emissions("can"):
            if busoff[0] <= t < busoff[1]:
                continue
            for node, name in CAN_NODES.items():
                if name not in self.place["can"] or not self.has(name) or self.dropped[name][f] or rng.random() < self.loss:
                    continue
                for m in encode_node_frames(node, imu_at(self.take, name, t, self.imus), np.zeros(3), 0xFF,
                                            self.count("can", k) & 0xFF):
                    can_t.append(self.start + t)
                    can_id.append(m.arbitration_id)
                    can_data.append(np.frombuffer(flip_bits(bytes(m.data), self.ber, rng), np.uint8))
        return can_t, can_id, can_data

    def slimevr_logs(self):
        from firmware_bridge.transports.slimevr import AXES_OFFSET
        from firmware_bridge.wire.slimevr import TrackerEncoder
        to_wire = quat.inv(AXES_OFFSET)            # the board turns Z-up to Y-up; the tracker sends Z-up
        out = {}
        for name in self.place["slimevr"]:
            log, enc = SerialLog(), TrackerEncoder(SLIMEVR_MACS[name])
            if self.start == 0:
                log.add(0.0, enc.sensor_info(0))
            before = self.count("slimevr", 0)             # rotations sent before: each 100th came with a battery
            enc.number = before + before // 100
            for k, t, f in self.emissions("slimevr", clock="hub"):
                if self.dropped[name][f] or self.rng.random() < self.loss:
                    enc.number += 1                    # a lost datagram still used its number
                    continue
                q = quat.mul(to_wire, imu_at(self.take, name, t, self.imus))
                log.add(self.start + t, flip_bits(enc.rotation(0, q), self.ber, self.rng))
                if k % 100 == 99:
                    log.add(self.start + t, enc.battery(3.9, 0.8))
            out[SLIMEVR_MACS[name]] = log
        return out

    def i2c_samples(self, on_i2c):
        """The waist BNO055's polls: times, orientations (NaN while it is dropped) and linear acceleration."""
        sig, fps = self.sig, self.fps
        i2c_t = np.arange(0.0, self.duration, 1.0 / RATES["i2c"]) if on_i2c else np.zeros(0)
        i2c_q = np.array([imu_at(self.take, "waist", t) for t in i2c_t]).reshape(-1, 4)
        i2c_a = np.array([signal_at(sig, fps, t)[5] for t in i2c_t]).reshape(-1, 3)
        if on_i2c:
            i2c_q = quat.normalize(np.array([signal_at(sig, fps, t)[4] for t in i2c_t]))
            gone = self.dropped["waist"][np.minimum((i2c_t * fps).astype(int), self.frames60 - 1)]
            i2c_q[gone] = np.nan                                   # the puck stops answering (see replay)
        return self.start + i2c_t, i2c_q, i2c_a
