"""slimevr://HOST:PORT?trackers=MAC/SENSOR:NAME,...[&accept=any]: the board answers SlimeVR trackers as
the SlimeVR server does, so their firmware and settings stay as they are (firmware_bridge/wire/slimevr.md).

    slimevr://0.0.0.0:6969?trackers=02:ed:9e:00:00:01/0:l_shin,02:ed:9e:00:00:01/1:r_shin

- A tracker searching for its server broadcasts a handshake (type 3); the board answers it (64 bytes,
  "Hey OVR =D 5") and from then on knows the tracker by its MAC. A new handshake from a known MAC (a
  restarted tracker) takes it over again, with its packet numbers from zero.
- Every 0.5 s each known tracker gets a heartbeat (type 1): the firmware drops a server it has not
  heard from for 3 s. SENSOR_INFO is acknowledged, FEATURE_FLAGS answered, PING_PONG echoed.
- Packet numbers must grow: a duplicate or an older packet is dropped and counted.
- Rotations (type 17, legacy 1 and 16, and bundles) of the configured MAC/sensor pairs become
  TrackerSamples, turned from the IMU's Z-up frame into ours (Y-up), as the server turns them; the
  calibration then handles mounting like any IMU's. Without a timestamp on the wire, the time the
  kernel received the datagram is the sample's time. Unconfigured trackers are answered (accept=any) or ignored, and
  listed in `trackers()` either way; they never feed the model.
Every datagram is untrusted: what does not parse is counted and dropped (firmware_bridge.wire.slimevr).
"""
import math
import select
import socket
import struct
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from edge import quat
from firmware_bridge.wire import slimevr as wire
from firmware_bridge.samples import TrackerSample
from firmware_bridge.transports.base import Source, TransportError

HEARTBEAT_S = 0.5
# The server's AXES_OFFSET: a quarter turn about -X takes the IMU's Z-up world to a Y-up one.
AXES_OFFSET = quat.from_axis_angle(np.array([1.0, 0.0, 0.0]), -math.pi / 2)


@dataclass
class Tracker:
    """What the board knows of one SlimeVR tracker (one MAC)."""
    mac: str
    address: tuple
    firmware: str = ""
    last_number: int = 0
    number_ahead: int = None         # a packet number far from the last, waiting for the next to confirm it
    sensors: dict = field(default_factory=dict)      # sensor id -> status (0 off, 1 ok, 2 error)
    battery: float = None                             # 0..1
    packets: int = 0
    first_seen: float = 0.0
    last_seen: float = 0.0
    handshakes: int = 0

    def rate(self, now):
        span = max(now - self.first_seen, 1e-3)
        return self.packets / span


def parse_tracker_map(text):
    """'02:ed:9e:00:00:01/0:l_shin,...' -> {(mac, sensor): name}. ValueError says what is wrong."""
    out = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        where, sep, name = item.strip().rpartition(":")
        mac, slash, sensor = where.partition("/")
        parts = mac.split(":")
        if (not sep or not slash or not name or len(parts) != 6 or not all(len(p) == 2 for p in parts)
                or not sensor.isdigit()):
            raise ValueError(f"expected MAC/SENSOR:NAME such as 02:ed:9e:00:00:01/0:l_shin, got {item!r}")
        try:
            bytes.fromhex("".join(parts))
        except ValueError:
            raise ValueError(f"{mac!r} is not a MAC address") from None
        out[(mac.lower(), int(sensor))] = name
    return out


# A packet number more than this from the last (10 s of packets at 100 Hz), ahead or behind, is believed
# only when the next packet follows on from it: one datagram whose number was damaged must not make
# every later one "old" (an edge soak with bit errors found a tracker dropped for good), and if one was
# believed (the first after a handshake has nothing to be checked against) the true ones win it back.
NUMBER_STEP_MAX = 1000
DATAGRAMS_PER_CALL = 1024     # one recv reads what is queued, but a flood cannot hold it


def tracker_names(parsed):
    try:
        return list(parse_tracker_map(parsed[3].get("trackers", "")).values())
    except ValueError as e:
        raise TransportError(f"trackers=: {e}") from None


class SlimeVRSource(Source):
    def __init__(self, host, port, mapping, accept_any=False, clock=time.monotonic):
        super().__init__(clock)
        self.stats.update({"unknown": 0, "dropped_old": 0, "corrupt_number": 0, "handshakes": 0, "ignored": 0})
        self.mapping, self.accept_any, self.clock = mapping, accept_any, clock
        self.known_macs = {mac for mac, _ in mapping}
        try:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.setblocking(False)
            # Room for what arrives between two reads (a tick, or a burst): a flood must be read and
            # counted, not overflow the buffer and take the real trackers' datagrams with it.
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
            self.sock.bind((host, port))
            # The kernel stamps each datagram when it arrives (SCM_TIMESTAMPNS): the wire has no time of
            # its own, and a datagram read at the next tick would otherwise be up to a frame late.
            self._stamps = hasattr(socket, "SO_TIMESTAMPNS")
            if self._stamps:
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_TIMESTAMPNS, 1)
        except OSError as e:
            raise TransportError(f"cannot listen for SlimeVR trackers on {host}:{port}: {e.strerror or e}; "
                                 f"is another SlimeVR server running, or the address not this board's?") from None
        self.address = self.sock.getsockname()
        self.by_address, self.by_mac = {}, {}
        self.pending = deque()
        self._last_heartbeat = 0.0

    def _recv_internal(self, timeout):
        """Heartbeats when due; then the next sample, reading the datagrams waiting (up to `timeout`
        for the first, and never longer than a heartbeat period)."""
        self._keep_up()
        if not self.pending:
            self._read_ready(HEARTBEAT_S if timeout is None else min(timeout, HEARTBEAT_S))
            self._keep_up()
        return self.pending.popleft() if self.pending else None

    def _read_ready(self, wait):
        """Read the datagrams waiting (waiting up to `wait` s for the first, at most DATAGRAMS_PER_CALL)."""
        ready, _, _ = select.select([self.sock], [], [], max(wait, 0.0))
        for _ in range(DATAGRAMS_PER_CALL if ready else 0):
            try:
                data, anc, _, addr = self.sock.recvmsg(2048, 64)
            except BlockingIOError:
                break
            self._handle(data, addr, self._arrival(anc))

    def _arrival(self, anc):
        """When the datagram arrived, on our clock: now minus its age by the kernel's stamp."""
        now = self.clock()
        for level, kind, raw in anc:
            if level == socket.SOL_SOCKET and kind == getattr(socket, "SCM_TIMESTAMPNS", -1) and len(raw) >= 16:
                sec, nsec = struct.unpack("qq", raw[:16])
                age = time.time() - (sec + nsec * 1e-9)
                return now - min(max(age, 0.0), 1.0)
        return now

    def _handle(self, data, addr, now=None):
        now = self.clock() if now is None else now
        try:
            packet = wire.parse(data)
        except wire.WireError:
            self.stats["corrupt"] += 1
            return
        if packet.kind == wire.HANDSHAKE:
            self._handshake(packet.items[0], addr, now)
            return
        t = self.by_address.get(addr)
        if t is None:                                   # never said hello: the server ignores it too
            self.stats["unknown"] += 1
            return
        far = packet.number != 0 and t.last_number and abs(packet.number - t.last_number) > NUMBER_STEP_MAX
        if far and not self._confirms(t, packet.number):
            self.stats["corrupt"] += 1                 # far from the last: believed when the next follows on
            self.stats["corrupt_number"] += 1
            return
        if not far and packet.number != 0 and packet.number <= t.last_number:
            self.stats["dropped_old"] += 1             # a duplicate, or older than what came
            return
        t.number_ahead = None
        t.last_number, t.last_seen = packet.number, now
        t.packets += 1
        if packet.kind == wire.PING_PONG:
            self._send(data, addr)
        elif packet.kind == wire.FEATURE_FLAGS:
            self._send(wire.feature_flags(), addr)
        for item in packet.items:
            if isinstance(item, wire.SensorInfo):
                t.sensors[item.sensor] = item.status
                self._send(wire.sensor_info_ack(item.sensor, item.status), addr)
            elif isinstance(item, wire.Battery):
                t.battery = item.level
            elif isinstance(item, wire.Rotation) and item.data_type == 1:
                name = self.mapping.get((t.mac, item.sensor))
                if name is None:
                    self.stats["ignored"] += 1
                    continue
                self.stats["frames"] += 1
                self.pending.append(TrackerSample(name, now, quat.normalize(quat.mul(AXES_OFFSET, item.quat)),
                                                  received=now))

    @staticmethod
    def _confirms(t, number):
        """Whether a number far from the last follows on from the one before it (then the tracker's
        numbers did jump); if not, it is the one to confirm next."""
        if t.number_ahead is not None and t.number_ahead < number <= t.number_ahead + NUMBER_STEP_MAX:
            return True
        t.number_ahead = number
        return False

    def _handshake(self, h, addr, now):
        self.stats["handshakes"] += 1
        mac = h.mac or f"ip:{addr[0]}:{addr[1]}"
        if mac not in self.known_macs and not self.accept_any:
            # Not ours: list it, but do not take it from a SlimeVR server that may be running too.
            t = self.by_mac.setdefault(mac, Tracker(mac, addr, h.firmware, first_seen=now))
            t.last_seen, t.handshakes = now, t.handshakes + 1
            return
        t = self.by_mac.get(mac)
        if t is None:
            t = self.by_mac[mac] = Tracker(mac, addr, h.firmware, first_seen=now)
        else:                                           # a restarted tracker, or one that moved
            self.by_address.pop(t.address, None)
            t.address, t.firmware, t.last_number, t.number_ahead = addr, h.firmware, 0, None
        t.last_seen, t.handshakes = now, t.handshakes + 1
        self.by_address[addr] = t
        self._send(wire.HANDSHAKE_REPLY, addr)

    def _keep_up(self):
        now = self.clock()
        if now - self._last_heartbeat < HEARTBEAT_S:
            return
        self._last_heartbeat = now
        for addr in self.by_address:
            self._send(wire.heartbeat(), addr)

    def _send(self, data, addr):
        try:
            self.sock.sendto(data, addr)
        except OSError:
            self.stats["errors"] += 1

    def trackers(self):
        """Every tracker heard: MAC -> {sensors, rate, battery, in_use, age} (for the status line)."""
        now = self.clock()
        return {mac: {"sensors": dict(t.sensors), "packets_per_s": round(t.rate(now), 1), "battery": t.battery,
                      "in_use": mac in self.known_macs, "age_s": round(now - t.last_seen, 2)}
                for mac, t in self.by_mac.items()}

    def _close_internal(self):
        self.sock.close()


def open(url, parsed, clock=time.monotonic, **_):
    _, netloc, _, query = parsed
    host, sep, port = netloc.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise TransportError(f"{url}: expected slimevr://HOST:PORT (e.g. slimevr://0.0.0.0:6969)")
    try:
        mapping = parse_tracker_map(query.get("trackers", ""))
    except ValueError as e:
        raise TransportError(f"{url}: trackers=: {e}") from None
    accept = query.get("accept", "configured")
    if accept not in ("configured", "any"):
        raise TransportError(f"{url}: accept= must be 'configured' or 'any', not {accept!r}")
    return SlimeVRSource(host, int(port), mapping, accept == "any", clock)
