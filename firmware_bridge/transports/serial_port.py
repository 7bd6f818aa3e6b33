"""The `serial` scheme: a tracker hub or the headset on a UART (the messages: firmware_bridge.wire.messages).

    serial:///dev/ttyUSB0?baud=921600&role=hub&trackers=0:waist,1:l_shin   TRACKER_SAMPLES only
    serial:///dev/ttyAMA0?role=headset              HEADSET_POSE only; send_pose() answers on the same link
    serial:///dev/ttyUSB0                           both (default), 460800 baud

`trackers` maps the hub's wire ids to tracker names (without it, id 0 is the waist).

Reads whatever bytes have arrived and feeds them to a FrameReader (one read per chunk, not one per
byte: pyserial's inter_byte_timeout does nothing on Linux, the COBS delimiter does the framing).
"""
from collections import deque
import time

import serial

from firmware_bridge.transports.base import DeviceUnavailable, Source, TransportError, id_names
from firmware_bridge.wire.messages import (DEFAULT_TRACKER_NAMES, HEADSET_POSE, TARGET, TRACKER_SAMPLES, FrameReader,
                                           PoseEncoder)

DEFAULT_BAUD = 460800
ROLES = {
    "hub": (TRACKER_SAMPLES,),
    "headset": (HEADSET_POSE, TARGET),
    "both": (TRACKER_SAMPLES, HEADSET_POSE, TARGET),
}
# A write that cannot drain within this time means the far end stopped reading: drop the frame
# rather than stall the pose loop.
WRITE_TIMEOUT = 0.05


def parse_tracker_names(query):
    """?trackers=0:waist,1:l_shin -> {0: 'waist', 1: 'l_shin'}; None without it (the default map)."""
    if "trackers" not in query:
        return None
    return id_names(query["trackers"], range(256), "trackers=0:waist,1:l_foot")


def tracker_names(parsed):
    names = parse_tracker_names(parsed[3])
    return list((DEFAULT_TRACKER_NAMES if names is None else names).values())


def open(url, parsed, tracker_names=None):
    """Source for 'serial://PORT?baud=B&role=hub|headset|both&trackers=ID:NAME,...'; `tracker_names`
    (a map) overrides the URL's."""
    _, netloc, path, query = parsed
    port = netloc + path                 # '/dev/ttyUSB0' from serial:///dev/ttyUSB0, 'COM3' from serial://COM3
    if not port:
        raise TransportError(f"{url!r} names no port: use e.g. serial:///dev/ttyUSB0?baud=460800")
    baud = query.get("baud", str(DEFAULT_BAUD))
    if not baud.isdigit() or int(baud) <= 0:
        raise TransportError(f"{url!r}: baud must be a positive integer, not {baud!r}")
    role = query.get("role", "both")
    if role not in ROLES:
        raise TransportError(f"{url!r}: role must be one of {', '.join(ROLES)}, not {role!r}")
    names = parse_tracker_names(query) if tracker_names is None else tracker_names
    return SerialSource(port, int(baud), role, tracker_names=names, url=url)


class SerialSource(Source):
    """TrackerSamples and HeadsetSamples from a serial port, and pose frames back to it."""

    def __init__(self, port, baud=DEFAULT_BAUD, role="both", tracker_names=None, url=""):
        super().__init__()
        self.url = url or f"serial://{port}?baud={baud}&role={role}"
        self.stats["sent"] = 0
        self.reader = FrameReader(accept=ROLES[role], tracker_names=tracker_names, stats=self.stats)
        self._ready = deque()            # decoded samples not yet returned by recv
        self._pose_seq = 0
        self._pose_encoder = None
        self._resync = False             # a write was cut short: end that partial frame first
        try:
            # exclusive: two programs reading one UART would each see half the bytes.
            self.port = serial.Serial(port, baud, timeout=0, write_timeout=WRITE_TIMEOUT, exclusive=True)
        except (serial.SerialException, ValueError, OSError) as error:
            raise DeviceUnavailable(
                f"cannot open serial port {port} at {baud} baud: {error}. Check that the device is "
                f"plugged in, the path is right, you may use it (the 'dialout' group) and no other "
                f"program has it open.") from error

    def _recv_internal(self, timeout):
        if not self._ready:
            self._read_available(timeout)
        return self._ready.popleft() if self._ready else None

    def _read_available(self, wait):
        """Read what has arrived, waiting up to `wait` seconds for the first byte."""
        try:
            if self.port.timeout != wait:
                self.port.timeout = wait
            chunk = self.port.read(max(1, self.port.in_waiting))
        except serial.SerialException as error:
            self.stats["errors"] += 1
            raise TransportError(f"serial port {self.port.port} failed: {error}") from error
        if chunk:
            received = time.monotonic()
            for message in self.reader.feed(chunk):
                message.received = received
                self._ready.append(message)

    def send(self, data):
        """Write encoded frames. False (and counted in errors) if the far end stopped reading and the
        write timed out: the frame may be cut off, so the next send starts with a 0x00 to end it."""
        if self._resync:
            data = b"\x00" + bytes(data)
        try:
            self.port.write(data)
        except serial.SerialTimeoutException:
            self.stats["errors"] += 1
            self._resync = True
            return False
        except serial.SerialException as error:
            self.stats["errors"] += 1
            raise TransportError(f"serial port {self.port.port} failed: {error}") from error
        self._resync = False
        self.stats["sent"] += 1
        return True

    def send_pose(self, frame):
        """Encode a PoseFrame with this link's running sequence number and send it."""
        if self._pose_encoder is None:          # the first pose: only a headset link sends any
            self._pose_encoder = PoseEncoder()
        data = self._pose_encoder.encode(frame, self._pose_seq)
        self._pose_seq = (self._pose_seq + 1) & 0xFFFF
        return self.send(data)

    def _close_internal(self):
        self.port.close()
