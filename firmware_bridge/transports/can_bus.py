"""The `can` scheme: IMU tracker nodes on a CAN bus, through python-can 4.x.

    source = open_source("can://socketcan/can0?nodes=1:waist,2:l_foot,3:r_foot")
    source = open_source("can://virtual/bus0")          # python-can's in-process bus (tests, simulator)
    sample = source.recv(timeout=0.02)                  # TrackerSample or None

URL: `can://INTERFACE/CHANNEL?nodes=ID:NAME,...&bitrate=BPS` -> `can.Bus(interface=INTERFACE,
channel=CHANNEL, bitrate=BPS)`. `nodes` maps node ids to tracker names; without it every node is
accepted and named "node<ID>"; with it, frames from other nodes count as unknown. `bitrate` is only
needed by interfaces that set it themselves (SocketCAN takes it from `ip link`).

Wire format (docs/can.md has the tables and a worked example): each tracker node sends one sample as
two classic 11-bit CAN frames with 8 data bytes, back to back:

    0x100 + node   quaternion w, x, y, z: int16 little-endian, 1/16384 (Q14)
    0x180 + node   linear acceleration x, y, z: int16 little-endian, 0.01 m/s^2; status u8; sequence u8

The quaternion frame has the lower ID, so it wins arbitration and leaves first; the board pairs the
next acceleration frame from the same node with it. The sequence number counts samples per node
(mod 256) and shows how many were lost. A sample's `t` is the quaternion frame's `msg.timestamp`
(the interface's receive time, in its own clock); `received` is the host's time.monotonic().

Frames are dropped and counted, never raised on: `stats["corrupt"]` counts frames with the wrong
length and quaternions that are not unit length (also split out as `wrong_dlc`, `bad_quaternion`);
`unknown_id` frames from other devices or unmapped nodes; `unpaired` frames whose partner was lost;
`lost` samples missing from a node's sequence; `errors` error frames and bus errors.
"""
import time

import can
import numpy as np

from firmware_bridge.samples import TrackerSample
from firmware_bridge.transports.base import Source, TransportError

QUAT_BASE_ID = 0x100
MOTION_BASE_ID = 0x180
MAX_NODE_ID = 0x7F                 # 7-bit node ids keep both frame ranges inside 0x100-0x1FF
FRAME_LENGTH = 8
QUAT_LSB = 16384                   # Q14: 1.0 = 16384
ACCEL_LSB_PER_MS2 = 100            # 0.01 m/s^2 per LSB, +-327 m/s^2 range
QUAT_NORM_TOLERANCE = 0.01         # Q14 rounding moves the norm by < 1e-4; more means a damaged frame
PAIR_WINDOW_S = 0.02               # an acceleration frame later than this after its quaternion is not its pair
FRAMES_AFTER_DEADLINE = 64         # recv drains what is already queued, but not an endless flood

BUS_HINTS = {
    "socketcan": "bring the interface up first: `sudo ip link set {channel} up type can bitrate 1000000` "
                 "(a virtual one: `sudo modprobe vcan && sudo ip link add dev {channel} type vcan && "
                 "sudo ip link set {channel} up`)",
    "udp_multicast": "python-can's udp_multicast interface needs msgpack: pip install msgpack",
}


# ---- frame layout ---------------------------------------------------------------------------------

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
    """[4] (w, x, y, z) -> 8 bytes, Q14 int16 little-endian. Normalised first: nodes send unit quaternions."""
    quat = np.asarray(quat, np.float64)
    norm = np.linalg.norm(quat)
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"cannot send quaternion {quat}")
    counts = np.clip(np.round(quat / norm * QUAT_LSB), -32768, 32767)
    return counts.astype("<i2").tobytes()


def unpack_quaternion(data):
    """8 bytes -> [4] quaternion as sent (not renormalised)."""
    return np.frombuffer(bytes(data), dtype="<i2").astype(np.float64) / QUAT_LSB


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


# ---- URL parts ------------------------------------------------------------------------------------

def parse_node_map(text):
    """'1:waist,2:l_foot' -> {1: 'waist', 2: 'l_foot'} (ids decimal or 0x hex); '' -> {}."""
    nodes = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        node_text, _, name = item.partition(":")
        try:
            node = int(node_text, 0)
        except ValueError:
            node = 0
        if not 1 <= node <= MAX_NODE_ID or not name:
            raise TransportError(f"nodes={text!r}: write ID:NAME pairs with ids 1-{MAX_NODE_ID}, "
                                 f"e.g. nodes=1:waist,2:l_foot")
        nodes[node] = name
    return nodes


def bus_arguments(netloc, path, query):
    """URL parts -> keyword arguments for can.Bus."""
    channel = path.strip("/")
    if not netloc or not channel:
        raise TransportError("a CAN URL names the python-can interface and channel: can://virtual/bus0, "
                             "can://socketcan/can0, can://udp_multicast/239.74.163.2")
    arguments = {"interface": netloc, "channel": channel}
    if "bitrate" in query:
        arguments["bitrate"] = int(query["bitrate"])
    return arguments


def open_bus(interface, channel, **options):
    """can.Bus(...), with errors that say what to do."""
    try:
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError, ValueError, ImportError) as error:
        hint = BUS_HINTS.get(interface, "see python-can's list of interfaces and what each needs")
        raise TransportError(f"cannot open CAN interface {interface!r} channel {channel!r} ({error}): "
                             f"{hint.format(channel=channel)}") from error


def open(url, parsed, bus=None, **bus_options):
    """Open the CAN source the URL names. `bus`: an open python-can bus to use instead (the source
    does not shut it down); `bus_options` go to can.Bus."""
    _, netloc, path, query = parsed
    node_names = parse_node_map(query.get("nodes", ""))
    owns_bus = bus is None
    if owns_bus:
        bus = open_bus(**bus_arguments(netloc, path, query), **bus_options)
    return CanSource(bus, node_names, url=url, owns_bus=owns_bus)


# ---- decoding -------------------------------------------------------------------------------------

def new_stats():
    return {"frames": 0, "corrupt": 0, "errors": 0, "wrong_dlc": 0, "bad_quaternion": 0,
            "unknown_id": 0, "unpaired": 0, "lost": 0}


class TrackerFrameDecoder:
    """Frames in, TrackerSamples out: checks each frame, pairs a node's quaternion and acceleration
    frames, counts what it drops. Independent of any bus, so recorded logs can be replayed through it."""

    def __init__(self, node_names=None, *, quat_tolerance=QUAT_NORM_TOLERANCE, pair_window=PAIR_WINDOW_S,
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
        if abs(np.linalg.norm(quat) - 1.0) > self.quat_tolerance:
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


# ---- the source -----------------------------------------------------------------------------------

class CanSource(Source):
    """TrackerSamples from the tracker nodes on one python-can bus."""

    def __init__(self, bus, node_names=None, *, url="", owns_bus=True, **decoder_options):
        super().__init__()
        self.stats = new_stats()
        self.url = url
        self.bus = bus
        self.owns_bus = owns_bus
        self.last_error = None
        self.decoder = TrackerFrameDecoder(node_names, stats=self.stats, **decoder_options)

    def recv(self, timeout=None):
        """The next complete sample, or None if none completed within `timeout` seconds (None: wait).
        Frames already queued when the time is up are still read."""
        deadline = None if timeout is None else time.monotonic() + timeout
        frames_after_deadline = 0
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            if remaining == 0.0:
                frames_after_deadline += 1
                if frames_after_deadline > FRAMES_AFTER_DEADLINE:
                    return None
            try:
                msg = self.bus.recv(remaining)
            except can.CanError as error:
                self._count_bus_error(error, remaining)
                if remaining is not None and time.monotonic() >= deadline:
                    return None
                continue
            if msg is None:
                return None
            sample = self.decoder.feed(msg, received=time.monotonic())
            if sample is not None:
                return sample

    def close(self):
        if self.owns_bus:
            self.bus.shutdown()
            self.owns_bus = False

    def _count_bus_error(self, error, remaining):
        self.stats["errors"] += 1
        self.last_error = f"{type(error).__name__}: {error}"
        # Do not spin on a bus that keeps failing (an interface that went down).
        time.sleep(0.01 if remaining is None else min(0.01, remaining))
