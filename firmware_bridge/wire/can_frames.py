"""CAN tracker frames: the layout of a tracker node's two frames and the decoder that pairs them
(docs beside: can.md, with the tables and a worked example).

Each tracker node sends one sample as two classic 11-bit CAN frames with 8 data bytes, back to back:

    0x100 + node   quaternion w, x, y, z: int16 little-endian, Q14 (q14.py)
    0x180 + node   linear acceleration x, y, z: int16 little-endian, 0.01 m/s^2; status u8; sequence u8

The quaternion frame has the lower ID, so it wins arbitration and leaves first; the decoder pairs the
next acceleration frame from the same node with it. The sequence number counts samples per node
(mod 256) and shows how many were lost. A sample's `t` is the quaternion frame's `msg.timestamp`
(the interface's receive time, in its own clock); `received` is the host's time.monotonic().

Frames are dropped and counted, never raised on: `stats["corrupt"]` counts frames with the wrong
length and quaternions that are not unit length (also split out as `wrong_dlc`, `bad_quaternion`);
`unknown_id` frames from other devices or unmapped nodes; `unpaired` frames whose partner was lost;
`lost` samples missing from a node's sequence; `errors` error frames and bus errors.
Independent of any bus: python-can `Message` objects in, TrackerSamples out.
"""
import time

import can
import numpy as np

from firmware_bridge.samples import TrackerSample
from firmware_bridge.wire import q14

QUAT_BASE_ID = 0x100
MOTION_BASE_ID = 0x180
MAX_NODE_ID = 0x7F                 # 7-bit node ids keep both frame ranges inside 0x100-0x1FF
FRAME_LENGTH = 8
ACCEL_LSB_PER_MS2 = 100            # 0.01 m/s^2 per LSB, +-327 m/s^2 range
PAIR_WINDOW_S = 0.02               # an acceleration frame later than this after its quaternion is not its pair


def quat_frame_id(node):
    return QUAT_BASE_ID + _checked_node(node)


def motion_frame_id(node):
    return MOTION_BASE_ID + _checked_node(node)


def _checked_node(node):
    if not 1 <= node <= MAX_NODE_ID:
        raise ValueError(f"node ids run from 1 to {MAX_NODE_ID}, not {node}")
    return node


def classify_frame(arbitration_id, is_extended_id=False):
    """-> ("quat", node), ("motion", node) or (None, None) for a frame that is not a tracker frame."""
    if is_extended_id:
        return None, None
    node = arbitration_id & MAX_NODE_ID
    if node == 0:
        return None, None
    if arbitration_id - node == QUAT_BASE_ID:
        return "quat", node
    if arbitration_id - node == MOTION_BASE_ID:
        return "motion", node
    return None, None


def pack_quaternion(quat):
    """[4] (w, x, y, z) -> 8 bytes, Q14 int16 little-endian, normalised first (q14.to_bytes)."""
    return q14.to_bytes(quat)


def unpack_quaternion(data):
    """8 bytes -> [4] quaternion as sent (not renormalised)."""
    return q14.from_bytes(data)


def pack_motion(accel, status, sequence):
    """Linear acceleration [3] m/s^2, status byte, sequence number -> 8 bytes."""
    accel = np.zeros(3) if accel is None else np.asarray(accel, np.float64)
    counts = np.clip(np.round(accel * ACCEL_LSB_PER_MS2), -32768, 32767).astype("<i2")
    return counts.tobytes() + bytes([status & 0xFF, sequence & 0xFF])


def unpack_motion(data):
    """8 bytes -> (accel [3] m/s^2, status, sequence)."""
    data = bytes(data)
    accel = np.frombuffer(data[:6], dtype="<i2").astype(np.float64) / ACCEL_LSB_PER_MS2
    return accel, data[6], data[7]


def encode_node_frames(node, quat, accel, status, sequence):
    """One tracker sample as the node sends it: [quaternion frame, acceleration frame]."""
    return [
        can.Message(arbitration_id=quat_frame_id(node), data=pack_quaternion(quat), is_extended_id=False),
        can.Message(arbitration_id=motion_frame_id(node), data=pack_motion(accel, status, sequence),
                    is_extended_id=False),
    ]


class TrackerNodeEncoder:
    """A tracker node's sending side (for the simulator): numbers its samples and builds their frames.
    `status` is the node's calibration byte in BNO055 CALIB_STAT layout (SYS, GYR, ACC, MAG, 2 bits each)."""

    def __init__(self, node):
        self.node = _checked_node(node)
        self.sequence = 0

    def frames(self, quat, accel=None, status=0xFF):
        messages = encode_node_frames(self.node, quat, accel, status, self.sequence)
        self.sequence = (self.sequence + 1) & 0xFF
        return messages


def new_stats():
    return {"frames": 0, "corrupt": 0, "errors": 0, "wrong_dlc": 0, "bad_quaternion": 0,
            "unknown_id": 0, "unpaired": 0, "lost": 0}


class TrackerFrameDecoder:
    """Frames in, TrackerSamples out: checks each frame, pairs a node's quaternion and acceleration
    frames, counts what it drops. Independent of any bus, so recorded logs can be replayed through it."""

    def __init__(self, node_names=None, *, quat_tolerance=q14.NORM_TOLERANCE, pair_window=PAIR_WINDOW_S,
                 stats=None):
        self.node_names = dict(node_names or {})
        self.quat_tolerance = quat_tolerance
        self.pair_window = pair_window
        self.stats = new_stats() if stats is None else stats
        self._pending_quat = {}            # node -> (quat, timestamp) waiting for its acceleration frame
        self._last_sequence = {}           # node -> last sequence number seen

    def feed(self, msg, received=None):
        """One frame -> the TrackerSample it completes, or None."""
        if msg.is_error_frame:
            self.stats["errors"] += 1
            return None
        kind, node = classify_frame(msg.arbitration_id, msg.is_extended_id)
        if kind is None or msg.is_remote_frame or (self.node_names and node not in self.node_names):
            self.stats["unknown_id"] += 1
            return None
        if msg.dlc != FRAME_LENGTH or len(msg.data) != FRAME_LENGTH:
            self._count_corrupt("wrong_dlc")
            return None
        if kind == "quat":
            self._take_quaternion(node, msg)
            return None
        return self._complete_sample(node, msg, time.monotonic() if received is None else received)

    def tracker_name(self, node):
        return self.node_names.get(node, f"node{node}")

    def _take_quaternion(self, node, msg):
        if self._pending_quat.pop(node, None) is not None:
            self.stats["unpaired"] += 1            # its acceleration frame never came
        quat = unpack_quaternion(msg.data)
        if not q14.is_unit(quat, self.quat_tolerance):
            self._count_corrupt("bad_quaternion")
            return
        self._pending_quat[node] = (quat, msg.timestamp)

    def _complete_sample(self, node, msg, received):
        accel, status, sequence = unpack_motion(msg.data)
        self._count_lost(node, sequence)
        pending = self._pending_quat.pop(node, None)
        if pending is not None and msg.timestamp - pending[1] > self.pair_window:
            self.stats["unpaired"] += 1            # a stale quaternion from an earlier sample
            pending = None
        if pending is None:
            self.stats["unpaired"] += 1
            return None
        quat, timestamp = pending
        self.stats["frames"] += 1
        return TrackerSample(tracker=self.tracker_name(node), t=timestamp, quat=quat / np.linalg.norm(quat),
                             accel=accel, status=status, received=received)

    def _count_lost(self, node, sequence):
        last = self._last_sequence.get(node)
        self._last_sequence[node] = sequence
        if last is not None:
            gap = (sequence - last) % 256
            self.stats["lost"] += max(gap - 1, 0)

    def _count_corrupt(self, reason):
        self.stats["corrupt"] += 1
        self.stats[reason] += 1
