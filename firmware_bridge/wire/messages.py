"""The messages of the board's serial links, and the stream reader (docs beside: protocol.md).

    tracker hub -> board    TRACKER_SAMPLES   IMU readings (one or more trackers per frame)
    headset     -> board    HEADSET_POSE      head and controller 6-DoF poses
    headset     -> board    TARGET            a point a joint should reach, with a radius and a time window
    board       -> headset  POSE_FRAME        the full-body pose the board computed

Each payload is one packed little-endian numpy record (read them beside the byte tables in
protocol.md), framed by framing.py; quaternions are Q14 (q14.py).

Reading a stream:  reader = FrameReader(); for message in reader.feed(chunk): ...
Writing a frame:   port.write(encode_pose_frame(frame, seq))
"""
from dataclasses import dataclass, field

import numpy as np

from edge.skeleton import NUM_JOINTS
from firmware_bridge.samples import HeadsetSample, TargetSample, TrackerSample
from firmware_bridge.wire import q14
from firmware_bridge.wire.framing import (DELIMITER, HEADSET_POSE, MAX_ENCODED_FRAME, MESSAGE_TYPES, POSE_FRAME,
                                          TARGET, TRACKER_SAMPLES, ProtocolError, TimestampUnwrapper, decode_frame,
                                          VERSION, encode_frame, seconds_to_us, sequence_gap)

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
# A headset or controller position further than this from the origin (in any axis) is not one any
# tracked space has: the frame is dropped and counted (kind "range"). It also keeps the body inside
# what POSE_FRAME can carry (the root in int16 millimetres: +-32.767 m). edge.pipeline's own guard uses
# the same limit for what reaches it by other ways.
POSITION_LIMIT_M = 30.0
INT16_MAX = q14.INT16_MAX
NO_ACCEL = -32768                        # all three accel axes at this value: the tracker sent none
MAX_TRACKER_SAMPLES = 32
MAX_SAMPLE_AGE_US = 65535

# POSE_FRAME ssi_flags bits (bits 3..7 are reserved and sent as 0).
SSI_IN_TRANSITION = 0x01                 # output is blending from one latent sample to another
SSI_SWITCHED = 0x02                      # a new sample was selected this frame
SSI_OUTLIER = 0x04                       # the current sample's cost was an outlier this frame

# Tracker ids on the wire -> TrackerSample.tracker. Id 0 is the waist puck; a deployment passes its
# own map (the same one at both ends) for the others.
DEFAULT_TRACKER_NAMES = {0: "waist"}

# ---------------------------------------------------------------------------------------------
# Payload layouts, one numpy record per message (packed, little-endian). They read like the byte
# tables in docs/protocol.md.

TRACKER_RECORD = np.dtype([
    ("id", "u1"),
    ("status", "u1"),                    # calibration / status bits, passed through
    ("age_us", "<u2"),                   # how long before the frame's t_us this reading was taken
    ("quat_q14", "<i2", 4),              # w, x, y, z
    ("accel_cm_s2", "<i2", 3),           # linear acceleration, sensor frame, 0.01 m/s^2
])

CONTROLLER_RECORD = np.dtype([
    ("valid", "u1"),                     # bit 0: tracked; other bits reserved
    ("pos_m", "<f4", 3),
    ("quat_q14", "<i2", 4),
])
HEADSET_RECORD = np.dtype([
    ("head_pos_m", "<f4", 3),
    ("head_quat_q14", "<i2", 4),
    ("controllers", CONTROLLER_RECORD, 2),   # left, right
])

TARGET_RECORD = np.dtype([
    ("target_id", "u1"),
    ("joint", "u1"),
    ("flags", "u1"),                         # bit 0: clear target_id
    ("reserved", "u1"),
    ("position_m", "<f4", 3),
    ("radius_m", "<f4"),
    ("start_ms", "<u2"),
    ("duration_ms", "<u2"),
])
TARGET_CLEAR = 0x01

POSE_RECORD = np.dtype([
    ("root_pos_mm", "<i2", 3),           # pelvis world position, millimetres
    ("rotations_q14", "<i2", (NUM_JOINTS, 4)),   # local rotations in edge.skeleton.JOINT_NAMES order
    ("contacts_u8", "u1", 2),            # left, right foot-contact probability x 255
    ("num_samples", "u1"),               # latent samples N in use
    ("ssi_flags", "u1"),
    ("trackers_lost", "<u2"),            # bit i set: tracker id i is lost
])

assert TRACKER_RECORD.itemsize == 18 and HEADSET_RECORD.itemsize == 62 and POSE_RECORD.itemsize == 180


@dataclass
class PoseFrame:
    """One board -> headset pose."""
    t: float                             # board clock, seconds
    root_pos: np.ndarray                 # [3] pelvis world position, metres
    rotations: np.ndarray                # [21,4] local joint rotations (w, x, y, z), JOINT_NAMES order
    contacts: np.ndarray = field(default_factory=lambda: np.zeros(2))   # [2] left, right, 0..1
    num_samples: int = 1
    ssi_flags: int = 0                   # SSI_* bits
    trackers_lost: int = 0               # bit i set: tracker id i is lost
    received: float = 0.0                # host time.monotonic() at reception (receiving side)
    held_s: float = 0.0                  # how long the board held the frame for SSI look-ahead (not on the wire)


# ---------------------------------------------------------------------------------------------
# Value checks.


def quat_from_q14(raw):
    """int16 Q14 [..., 4] -> unit quaternions. Raises ProtocolError when a norm is far from 1
    (not a rotation); normalises the rest, which removes the rounding of Q14."""
    q = q14.from_q14(raw)
    off = q14.norm_error(q)
    if np.any(off > q14.NORM_TOLERANCE):
        raise ProtocolError(f"quaternion norm {float(np.linalg.norm(q.reshape(-1, 4)[np.argmax(off)])):.3f} is not 1",
                            "quaternion")
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def finite_float32(values, what):
    """values as float32 for the wire; raises ValueError if any is NaN or does not fit."""
    values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(values)) or np.any(np.abs(values) > np.finfo(np.float32).max):
        raise ValueError(f"cannot encode {what}: not a finite float32")
    return values.astype("<f4")


def checked_finite(values, what):
    """A position as float32 from the wire -> float64; raises ProtocolError on NaN or infinity (checked
    before the cast: casting a signalling NaN raises a floating-point warning) and on a coordinate
    beyond POSITION_LIMIT_M (a finite 3e38 would poison the recurrent state just the same)."""
    if not np.all(np.isfinite(values)):
        raise ProtocolError(f"{what} is NaN or infinite", "value")
    if np.any(np.abs(values) > POSITION_LIMIT_M):
        raise ProtocolError(f"{what} is {float(np.abs(values).max()):.3g} m from the origin, beyond the "
                            f"{POSITION_LIMIT_M:g} m any tracked space spans", "range")
    return np.asarray(values, dtype=np.float64)


def check_payload_size(payload, size, what):
    if len(payload) != size:
        raise ProtocolError(f"{what} payload is {len(payload)} bytes, expected {size}")


def check_range(value, what, limit=255):
    """An integer field for the wire; raises ValueError if it does not fit 0..limit."""
    if not 0 <= int(value) <= limit:
        raise ValueError(f"{what} {value} does not fit 0..{limit}")
    return int(value)


# ---------------------------------------------------------------------------------------------
# TRACKER_SAMPLES (hub -> board): count u8, then `count` TRACKER_RECORDs.


def tracker_name(wire_id, names=None):
    """Wire id -> TrackerSample.tracker ("waist", or "tracker<id>" for ids the map does not name)."""
    names = DEFAULT_TRACKER_NAMES if names is None else names
    return names.get(wire_id, f"tracker{wire_id}")


def tracker_id(name, names=None):
    """Inverse of tracker_name; raises ValueError for a name with no id."""
    names = DEFAULT_TRACKER_NAMES if names is None else names
    for wire_id, known in names.items():
        if known == name:
            return wire_id
    number = name.removeprefix("tracker")
    if number != name and number.isdigit() and int(number) < 256:
        return int(number)
    raise ValueError(f"no wire id for tracker {name!r}: add it to tracker_names")


def encode_tracker_samples(samples, seq, tracker_names=None):
    """TrackerSamples -> one TRACKER_SAMPLES frame. The frame is stamped with the newest sample's
    time; each record carries its age relative to that (so all must lie within 65.535 ms)."""
    if not 1 <= len(samples) <= MAX_TRACKER_SAMPLES:
        raise ValueError(f"a TRACKER_SAMPLES frame carries 1..{MAX_TRACKER_SAMPLES} samples, not {len(samples)}")
    sample_us = [round(s.t * 1e6) for s in samples]
    frame_us = max(sample_us)
    records = np.zeros(len(samples), TRACKER_RECORD)
    for record, sample, t_us in zip(records, samples, sample_us, strict=True):
        record["id"] = tracker_id(sample.tracker, tracker_names)
        record["status"] = check_range(sample.status, "status")
        record["age_us"] = check_range(frame_us - t_us, "sample age (us)", MAX_SAMPLE_AGE_US)
        record["quat_q14"] = q14.to_q14(sample.quat)
        record["accel_cm_s2"] = accel_to_wire(sample.accel)
    payload = bytes([len(samples)]) + records.tobytes()
    return encode_frame(TRACKER_SAMPLES, seq, frame_us, payload)


def accel_to_wire(accel):
    """m/s^2 [3] or None -> int16 0.01 m/s^2 (saturating at +-327.67 m/s^2; NO_ACCEL x3 for None)."""
    if accel is None:
        return np.full(3, NO_ACCEL)
    accel = np.asarray(accel, dtype=np.float64)
    if not np.all(np.isfinite(accel)):
        raise ValueError("cannot encode an acceleration that is NaN or infinite")
    return np.clip(np.round(accel * 100.0), -INT16_MAX, INT16_MAX)


def accel_from_wire(raw):
    """int16 0.01 m/s^2 [3] -> m/s^2, or None when all three axes are NO_ACCEL."""
    if np.all(raw == NO_ACCEL):
        return None
    if np.any(raw == NO_ACCEL):
        raise ProtocolError("acceleration mixes the 'not sent' marker with values", "value")
    return raw.astype(np.float64) / 100.0


def decode_tracker_samples(payload, t=0.0, tracker_names=None):
    """TRACKER_SAMPLES payload -> [TrackerSample]; `t` is the frame's time in seconds."""
    if not payload:
        raise ProtocolError("TRACKER_SAMPLES payload is empty")
    count = payload[0]
    if not 1 <= count <= MAX_TRACKER_SAMPLES:
        raise ProtocolError(f"TRACKER_SAMPLES count {count} is not 1..{MAX_TRACKER_SAMPLES}")
    check_payload_size(payload, 1 + count * TRACKER_RECORD.itemsize, "TRACKER_SAMPLES")
    records = np.frombuffer(payload, TRACKER_RECORD, offset=1)
    quats = quat_from_q14(records["quat_q14"])
    return [TrackerSample(tracker=tracker_name(int(r["id"]), tracker_names),
                          t=t - int(r["age_us"]) * 1e-6,
                          quat=quat,
                          accel=accel_from_wire(r["accel_cm_s2"]),
                          status=int(r["status"]))
            for r, quat in zip(records, quats, strict=True)]


# ---------------------------------------------------------------------------------------------
# HEADSET_POSE (headset -> board): one HEADSET_RECORD.


def encode_headset_pose(sample, seq):
    """HeadsetSample -> one HEADSET_POSE frame. An untracked controller is sent as position 0 and
    the identity rotation (its pose has no meaning)."""
    record = np.zeros((), HEADSET_RECORD)
    record["head_pos_m"] = finite_float32(sample.head_pos, "head position")
    record["head_quat_q14"] = q14.to_q14(sample.head_rot)
    for hand in range(2):
        controller = record["controllers"][hand]
        valid = bool(sample.hand_valid[hand])
        controller["valid"] = int(valid)
        controller["pos_m"] = finite_float32(sample.hand_pos[hand], "controller position") if valid else 0.0
        controller["quat_q14"] = q14.to_q14(sample.hand_rot[hand] if valid else IDENTITY)
    return encode_frame(HEADSET_POSE, seq, seconds_to_us(sample.t), record.tobytes())


def decode_headset_pose(payload, t=0.0):
    """HEADSET_POSE payload -> HeadsetSample; `t` is the frame's time in seconds."""
    check_payload_size(payload, HEADSET_RECORD.itemsize, "HEADSET_POSE")
    record = np.frombuffer(payload, HEADSET_RECORD)[0]
    controllers = record["controllers"]
    valid = (controllers["valid"] & 1).astype(bool)
    hand_pos = np.zeros((2, 3))
    hand_rot = np.tile(IDENTITY, (2, 1))
    for hand in np.flatnonzero(valid):       # an untracked controller's bytes are ignored
        hand_pos[hand] = checked_finite(controllers["pos_m"][hand], "controller position")
        hand_rot[hand] = quat_from_q14(controllers["quat_q14"][hand])
    return HeadsetSample(t=t,
                         head_pos=checked_finite(record["head_pos_m"], "head position"),
                         head_rot=quat_from_q14(record["head_quat_q14"]),
                         hand_pos=hand_pos, hand_rot=hand_rot, hand_valid=valid)


# ---------------------------------------------------------------------------------------------
# POSE_FRAME (board -> headset): one POSE_RECORD. Every field is an integer, so no bit pattern can
# decode to NaN; the root in millimetres saturates at +-32.767 m, far beyond any play space.


def pose_record(frame, record=None):
    """PoseFrame -> its POSE_FRAME payload as a POSE_RECORD, filled into `record` when one is given (a
    sender that reuses one allocates nothing per frame). Raises ValueError on NaN or out-of-range counters."""
    rotations = np.asarray(frame.rotations)
    if rotations.shape != (NUM_JOINTS, 4):
        raise ValueError(f"rotations must be [{NUM_JOINTS},4] quaternions, not {rotations.shape}")
    root = np.asarray(frame.root_pos, dtype=np.float64)
    contacts = np.asarray(frame.contacts, dtype=np.float64)
    if not (np.all(np.isfinite(root)) and np.all(np.isfinite(contacts))):
        raise ValueError("cannot encode a pose frame with a NaN or infinite root or contact")
    record = np.zeros((), POSE_RECORD) if record is None else record
    record["root_pos_mm"] = np.clip(np.round(root * 1000.0), -INT16_MAX, INT16_MAX)
    record["rotations_q14"] = q14.to_q14(rotations)
    record["contacts_u8"] = np.round(np.clip(contacts, 0.0, 1.0) * 255.0)
    record["num_samples"] = check_range(frame.num_samples, "num_samples")
    record["ssi_flags"] = check_range(frame.ssi_flags, "ssi_flags")
    record["trackers_lost"] = check_range(frame.trackers_lost, "trackers_lost", 0xFFFF)
    return record


def encode_pose_frame(frame, seq):
    """PoseFrame -> one POSE_FRAME frame. Raises ValueError on NaN or out-of-range counters."""
    return encode_frame(POSE_FRAME, seq, seconds_to_us(frame.t), pose_record(frame).tobytes())


class PoseEncoder:
    """encode_pose_frame for a sender that sends every tick: the compiled core (edge.native's
    ep_encode_pose, the same bytes, a few microseconds) writing into one buffer, so a frame allocates
    nothing; numpy's encode_pose_frame where the core is not there. encode() returns a memoryview of
    the frame, good until the next call. Raises ValueError as encode_pose_frame does."""

    def __init__(self):
        from edge import native
        self._native, self._lib = native, native.load()
        self._out = np.zeros(2 * POSE_RECORD.itemsize + 64, np.uint8)
        self._view = memoryview(self._out)
        self._addr = native.addr(self._out)
        self._bound = [(None, 0)] * 3        # (array, address) last passed as rotations, root, contacts

    def _address(self, k, a, shape):
        """The address of a float64 C-contiguous array of `shape` (taken once per array object), or None."""
        held, address = self._bound[k]
        if a is held:
            return address
        try:
            address = self._native.checked_addr(a, np.float64, shape)
        except (TypeError, ValueError):         # not an array the core can read: the numpy encoder takes it
            return None
        self._bound[k] = (a, address)
        return address

    def encode(self, frame, seq):
        rot = self._address(0, frame.rotations, (NUM_JOINTS, 4))
        root = self._address(1, frame.root_pos, (3,))
        contacts = self._address(2, frame.contacts, (2,))
        if self._lib is None or rot is None or root is None or contacts is None:
            return memoryview(encode_pose_frame(frame, seq))
        n = self._lib.ep_encode_pose(VERSION, POSE_FRAME, seq & 0xFFFF, seconds_to_us(frame.t), root, rot, NUM_JOINTS,
                                     contacts, check_range(frame.num_samples, "num_samples"),
                                     check_range(frame.ssi_flags, "ssi_flags"),
                                     check_range(frame.trackers_lost, "trackers_lost", 0xFFFF), self._addr, len(self._out))
        if n == -1:
            raise ValueError("cannot encode a pose frame with a NaN or infinite root or contact")
        if n == -2:
            raise ValueError("cannot encode a quaternion that is NaN, infinite or zero")
        if n < 0:
            raise ValueError(f"the compiled pose encoder refused the frame ({n})")
        return self._view[:n]


def decode_pose_frame(payload, t=0.0):
    """POSE_FRAME payload -> PoseFrame; `t` is the frame's time in seconds."""
    check_payload_size(payload, POSE_RECORD.itemsize, "POSE_FRAME")
    record = np.frombuffer(payload, POSE_RECORD)[0]
    return PoseFrame(t=t,
                     root_pos=record["root_pos_mm"] / 1000.0,
                     rotations=quat_from_q14(record["rotations_q14"]),
                     contacts=record["contacts_u8"] / 255.0,
                     num_samples=int(record["num_samples"]),
                     ssi_flags=int(record["ssi_flags"]),
                     trackers_lost=int(record["trackers_lost"]))


# ---------------------------------------------------------------------------------------------
# TARGET (headset -> board): one TARGET_RECORD. Its values are a request, decoded as sent: the board
# refuses an unsafe one (non-finite, unknown joint, out of reach) with a reason (edge.refine).


def encode_target(target, seq):
    """TargetSample -> one TARGET frame."""
    record = np.zeros((), TARGET_RECORD)
    record["target_id"] = check_range(target.target_id, "target_id")
    record["joint"] = check_range(target.joint, "joint")
    record["flags"] = TARGET_CLEAR if target.clear else 0
    record["position_m"] = np.asarray(target.position, np.float32)
    record["radius_m"] = np.float32(target.radius)
    record["start_ms"] = check_range(round(target.start * 1000), "start_ms", 0xFFFF)
    record["duration_ms"] = check_range(round(target.duration * 1000), "duration_ms", 0xFFFF)
    return encode_frame(TARGET, seq, seconds_to_us(target.t), record.tobytes())


def decode_target(payload, t=0.0):
    """TARGET payload -> TargetSample; `t` is the frame's time in seconds."""
    check_payload_size(payload, TARGET_RECORD.itemsize, "TARGET")
    record = np.frombuffer(payload, TARGET_RECORD)[0]
    with np.errstate(invalid="ignore"):     # a signalling NaN from the wire is quieted by the cast, silently:
        position = record["position_m"].astype(np.float64)   # it is refused later as non-finite
    return TargetSample(t=t, target_id=int(record["target_id"]), joint=int(record["joint"]),
                        position=position, radius=float(record["radius_m"]),
                        start=int(record["start_ms"]) / 1000.0, duration=int(record["duration_ms"]) / 1000.0,
                        clear=bool(record["flags"] & TARGET_CLEAR))


# ---------------------------------------------------------------------------------------------
# Whole messages and the stream.


def decode_messages(frame, t=None, tracker_names=None):
    """A checked Frame -> its messages (a list: one TRACKER_SAMPLES frame holds several samples).
    `t` is the frame's time in seconds (default: the raw header timestamp, not unwrapped)."""
    t = frame.t_us * 1e-6 if t is None else t
    if frame.msg_type == TRACKER_SAMPLES:
        return decode_tracker_samples(frame.payload, t, tracker_names)
    if frame.msg_type == HEADSET_POSE:
        return [decode_headset_pose(frame.payload, t)]
    if frame.msg_type == TARGET:
        return [decode_target(frame.payload, t)]
    return [decode_pose_frame(frame.payload, t)]


class FrameReader:
    """Decodes a byte stream fed in chunks of any size; never raises on bad input.

    feed(chunk) returns the messages (TrackerSample, HeadsetSample, PoseFrame) of every frame the
    chunk completed, with times on one unwrapped clock per message type. `stats` counts:
      frames       good frames decoded
      corrupt      frames dropped: bad COBS, CRC, length, version, type or value (see last_error),
                   also counted by ProtocolError.kind as corrupt_framing, corrupt_quaternion,
                   corrupt_range and corrupt_value
      unexpected   good frames of a type this reader does not accept
      missed       frames lost according to sequence numbers (estimate)
      clock_jumps  device clock jumps the next frame confirmed (backwards, or forward by over a second)
      clock_unconfirmed  frames dropped because their clock jumped (framing.TimestampUnwrapper): a
                   real jump costs the one frame that made it, a single wrong timestamp only itself
    Pass a Source's `stats` dict to count straight into it.
    """

    def __init__(self, accept=tuple(MESSAGE_TYPES), tracker_names=None, stats=None):
        self.accept = frozenset(accept)
        self.tracker_names = tracker_names
        self.stats = {} if stats is None else stats
        for key in ("frames", "corrupt", "unexpected", "missed", "clock_jumps", "clock_unconfirmed"):
            self.stats.setdefault(key, 0)
        self.last_error = ""
        self._pending = bytearray()      # bytes of the frame still being received
        self._skipping = False           # inside an over-long frame already counted as corrupt
        self._clocks = {}                # message type -> TimestampUnwrapper
        self._last_seq = {}              # message type -> last sequence number

    def feed(self, data):
        messages = []
        self._pending += data
        *complete, self._pending = self._pending.split(DELIMITER)
        for encoded in complete:
            if self._skipping:           # the tail of the over-long frame
                self._skipping = False
            elif encoded:                # empty: two delimiters in a row, allowed as a resync
                messages += self._decode(bytes(encoded))
        if len(self._pending) > MAX_ENCODED_FRAME:
            if not self._skipping:
                self._count_corrupt(f"no delimiter within {MAX_ENCODED_FRAME} bytes")
            self._skipping = True
            self._pending.clear()
        return messages

    def _decode(self, encoded):
        try:
            frame = decode_frame(encoded)
            if frame.msg_type not in self.accept:
                self.stats["unexpected"] += 1
                return []
            # Times come back relative to the frame; the clock only advances on a good frame.
            messages = decode_messages(frame, 0.0, self.tracker_names)
        except ProtocolError as error:
            self._count_corrupt(str(error), error.kind)
            return []
        self._count_missed(frame)
        t = self._unwrap(frame)
        if t is None:                    # its clock jumped: believed once the next frame follows on
            self.stats["clock_unconfirmed"] += 1
            return []
        self.stats["frames"] += 1
        for message in messages:
            message.t += t
        return messages

    def _count_corrupt(self, reason, kind="framing"):
        self.stats["corrupt"] += 1
        self.stats[f"corrupt_{kind}"] = self.stats.get(f"corrupt_{kind}", 0) + 1
        self.last_error = reason

    def _count_missed(self, frame):
        last = self._last_seq.get(frame.msg_type)
        if last is not None:
            self.stats["missed"] += sequence_gap(last, frame.seq)
        self._last_seq[frame.msg_type] = frame.seq

    def _unwrap(self, frame):
        clock = self._clocks.setdefault(frame.msg_type, TimestampUnwrapper())
        t = clock.unwrap(frame.t_us)
        self.stats["clock_jumps"] += int(clock.jumped)
        return t
