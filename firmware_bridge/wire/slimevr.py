"""The SlimeVR tracker protocol on the wire (UDP, port 6969): parse what trackers send, build what the
server answers. Every field is validated; a packet that does not parse raises WireError.

Followed from the sources (firmware_bridge/wire/slimevr.md has the byte tables and test vectors):
- firmware SlimeVR/SlimeVR-Tracker-ESP `src/network/connection.cpp` and `packets.h`;
- server SlimeVR/SlimeVR-Server `server/core/.../tracking/trackers/udp/UDPProtocolParser.kt`,
  `UDPPacket.kt` and `UDPDevice.kt`.

Every integer and float is big-endian. A packet is u32 type, u64 packet number, then its fields;
a tracker's discovery handshake has packet number 0; inside a bundle (type 100) each packet is a u16
length and the packet without its number (type 101, compact: u8 length, u8 type). Quaternions are
float32 x, y, z, w. The server answers a handshake with 64 bytes, 3 then "Hey OVR =D 5", and sends
u32 type, u64 0, fields (heartbeat: type 1).
"""
import struct
from dataclasses import dataclass, field

import numpy as np

PORT = 6969

HEARTBEAT = 0
ROTATION = 1                # legacy: sensor 0's quaternion
HANDSHAKE = 3
ACCEL = 4
PING_PONG = 10
BATTERY_LEVEL = 12
ERROR = 14
SENSOR_INFO = 15
ROTATION_2 = 16             # legacy: sensor 1's quaternion
ROTATION_DATA = 17
SIGNAL_STRENGTH = 19
TEMPERATURE = 20
FEATURE_FLAGS = 22
BUNDLE = 100
BUNDLE_COMPACT = 101

SERVER_HEARTBEAT = 1        # server -> tracker: the tracker answers with a HEARTBEAT
HANDSHAKE_REPLY = bytes([3]) + b"Hey OVR =D 5" + bytes(64 - 13)
MAX_PACKET = 1500           # a UDP payload on Ethernet/Wi-Fi; longer datagrams are not from a tracker
MAX_BUNDLED = 64
QUAT_NORM_TOLERANCE = 0.05  # |q| must be within 1 +- this (floats from a fusion filter are unit)


class WireError(ValueError):
    """A packet that does not parse: what was wrong, in a few words."""


@dataclass
class Handshake:
    board: int
    imu: int
    mcu: int
    firmware_build: int
    firmware: str
    mac: str                # "02:ed:9e:00:00:01", lower case; "" when the tracker sent none


@dataclass
class Rotation:
    sensor: int
    quat: np.ndarray        # [4] (w, x, y, z), unit
    data_type: int = 1      # 1 normal, 2 correction
    accuracy: int = 0


@dataclass
class Acceleration:
    sensor: int
    accel: np.ndarray       # [3] m/s^2


@dataclass
class Battery:
    voltage: float
    level: float            # 0..1 (firmware sends a fraction)


@dataclass
class SensorInfo:
    sensor: int
    status: int             # 0 disconnected, 1 ok, 2 error
    imu: int = 0


@dataclass
class Packet:
    """One parsed datagram: its type and number, and what it carried (several for a bundle)."""
    kind: int
    number: int
    items: list = field(default_factory=list)   # Handshake / Rotation / Acceleration / Battery / SensorInfo


def _take(buf, pos, fmt, what):
    size = struct.calcsize(fmt)
    if pos + size > len(buf):
        raise WireError(f"{what}: packet ends after {len(buf)} bytes")
    return struct.unpack_from(fmt, buf, pos), pos + size


def _finite(values, what):
    if not np.all(np.isfinite(values)):
        raise WireError(f"{what} is NaN or infinite")
    return values


def _sensor(s):
    if s > 127:
        raise WireError(f"sensor id {s} is not a sensor (0..127)")
    return s


def _quat(x, y, z, w, what="quaternion"):
    q = np.array([w, x, y, z], dtype=np.float64)
    _finite(q, what)
    n = float(np.sqrt(q @ q))
    if abs(n - 1.0) > QUAT_NORM_TOLERANCE:
        raise WireError(f"{what} has norm {n:.3f}, not 1")
    return q / n


def _body(kind, buf, pos):
    """The fields of one packet of `kind` from buf[pos:] -> list of items (unknown kinds: none)."""
    if kind == ROTATION_DATA:
        (sensor, dtype, x, y, z, w, acc), _ = _take(buf, pos, ">BBffffB", "rotation data")
        if dtype not in (1, 2):
            raise WireError(f"rotation data type {dtype} is neither 1 (normal) nor 2 (correction)")
        return [Rotation(_sensor(sensor), _quat(x, y, z, w), dtype, acc)]
    if kind in (ROTATION, ROTATION_2):      # legacy firmware: a quaternion for sensor 0 or 1
        (x, y, z, w), _ = _take(buf, pos, ">ffff", "legacy rotation")
        return [Rotation(0 if kind == ROTATION else 1, _quat(x, y, z, w))]
    if kind == ACCEL:
        (ax, ay, az), p = _take(buf, pos, ">fff", "acceleration")
        sensor = buf[p] if p < len(buf) else 0       # owoTrack sends no sensor id
        a = _finite(np.array([ax, ay, az], dtype=np.float64), "acceleration")
        if np.abs(a).max() > 1000.0:
            raise WireError("acceleration beyond 1000 m/s^2")
        return [Acceleration(_sensor(sensor), a)]
    if kind == BATTERY_LEVEL:
        (v,), p = _take(buf, pos, ">f", "battery")
        if p + 4 <= len(buf):
            (level,), _ = _take(buf, p, ">f", "battery")
        else:                                         # older firmware: the level alone
            v, level = 0.0, v
        _finite(np.array([v, level]), "battery")
        if not (0.0 <= level <= 1.5 and 0.0 <= v <= 10.0):
            raise WireError(f"battery {v:.2f} V at {level:.2f} is out of range")
        return [Battery(float(v), float(min(level, 1.0)))]
    if kind == SENSOR_INFO:
        (sensor, status), p = _take(buf, pos, ">BB", "sensor info")
        imu = buf[p] if p < len(buf) else 0
        if status > 2:
            raise WireError(f"sensor status {status} is not 0, 1 or 2")
        return [SensorInfo(_sensor(sensor), status, imu)]
    return []       # heartbeat, ping, feature flags, signal, temperature, ...: nothing the model reads


def parse_handshake(buf):
    """A tracker's discovery packet (type 3, number 0) -> Handshake."""
    (board, imu, mcu, _, _, _, build, n), p = _take(buf, 12, ">iiiiiiiB", "handshake")
    if p + n > len(buf):
        raise WireError("handshake: firmware version longer than the packet")
    firmware = bytes(buf[p:p + n]).split(b"\0")[0].decode("ascii", "replace")
    p += n
    mac = ""
    if p + 6 <= len(buf):
        raw = bytes(buf[p:p + 6])
        mac = "" if raw == bytes(6) else ":".join(f"{b:02x}" for b in raw)
    return Handshake(board, imu, mcu, build, firmware, mac)


def parse(buf):
    """One datagram from a tracker -> Packet. Raises WireError for anything malformed."""
    if not 12 <= len(buf) <= MAX_PACKET:
        raise WireError(f"datagram of {len(buf)} bytes (a packet is 12..{MAX_PACKET})")
    (kind, number), pos = _take(buf, 0, ">IQ", "header")
    if kind == HANDSHAKE:
        if number != 0:
            raise WireError("handshake with a non-zero packet number")
        return Packet(kind, 0, [parse_handshake(buf)])
    if kind in (BUNDLE, BUNDLE_COMPACT):
        items, count = [], 0
        while pos < len(buf):
            if kind == BUNDLE:
                (n,), pos = _take(buf, pos, ">H", "bundle length")
                if n < 4 or pos + n > len(buf):
                    raise WireError(f"bundled packet of {n} bytes does not fit")
                (inner,), _ = _take(buf, pos, ">I", "bundled type")
                items += _body(inner, buf[:pos + n], pos + 4)
            else:
                (n,), pos = _take(buf, pos, ">B", "bundle length")
                if n < 1 or pos + n > len(buf):
                    raise WireError(f"bundled packet of {n} bytes does not fit")
                items += _body(buf[pos], buf[:pos + n], pos + 1)
            pos += n
            count += 1
            if count > MAX_BUNDLED:
                raise WireError(f"bundle of more than {MAX_BUNDLED} packets")
        return Packet(kind, number, items)
    return Packet(kind, number, _body(kind, buf, pos))


# ------------------------------------------------------------------ what the server (the board) sends

def server_packet(kind, payload=b""):
    """u32 type, u64 packet number (always 0 towards trackers), payload."""
    return struct.pack(">IQ", kind, 0) + payload


def heartbeat():
    return server_packet(SERVER_HEARTBEAT)


def sensor_info_ack(sensor, status):
    """The server's acknowledgement of a SENSOR_INFO: u32 type, sensor id, status (no packet number)."""
    return struct.pack(">IBB", SENSOR_INFO, sensor, status)


def feature_flags(flags=b"\x01"):
    """The server's feature flags (bit 0: bundles supported)."""
    return server_packet(FEATURE_FLAGS, flags)


# ------------------------------------------------------------------ what a tracker sends (the simulator)

class TrackerEncoder:
    """A SlimeVR tracker's sending side: numbers its packets and builds them as the firmware does."""

    def __init__(self, mac, firmware="0.5.0", build=17, board=2, imu=8, mcu=2):
        self.mac = bytes(int(x, 16) for x in mac.split(":"))
        self.firmware, self.build, self.board, self.imu, self.mcu = firmware, build, board, imu, mcu
        self.number = 0

    def _next(self):
        self.number += 1
        return self.number

    def handshake(self):
        self.number = 0
        v = self.firmware.encode("ascii")
        return (struct.pack(">IQiiiiiiiB", HANDSHAKE, 0, self.board, self.imu, self.mcu, 0, 0, 0, self.build, len(v))
                + v + self.mac)

    def sensor_info(self, sensor, status=1):
        return struct.pack(">IQBBB", SENSOR_INFO, self._next(), sensor, status, self.imu)

    @staticmethod
    def _rotation_body(sensor, quat, accuracy=0):
        w, x, y, z = (float(v) for v in quat)
        return struct.pack(">BBffffB", sensor, 1, x, y, z, w, accuracy)

    def rotation(self, sensor, quat):
        return struct.pack(">IQ", ROTATION_DATA, self._next()) + self._rotation_body(sensor, quat)

    def legacy_rotation(self, quat):
        w, x, y, z = (float(v) for v in quat)
        return struct.pack(">IQffff", ROTATION, self._next(), x, y, z, w)

    def battery(self, voltage, level):
        return struct.pack(">IQff", BATTERY_LEVEL, self._next(), voltage, level)

    def heartbeat(self):
        return struct.pack(">IQ", HEARTBEAT, self._next())

    def bundle(self, rotations):
        """Several sensors' rotation data in one datagram, as the firmware bundles them."""
        out = struct.pack(">IQ", BUNDLE, self._next())
        for sensor, quat in rotations:
            inner = struct.pack(">I", ROTATION_DATA) + self._rotation_body(sensor, quat)
            out += struct.pack(">H", len(inner)) + inner
        return out
