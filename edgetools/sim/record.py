"""`edge record`: capture what real transports carry into a session file that `edge replay` plays back.

Serial links are recorded as the exact frames on the wire (split at the 0x00 delimiters, delimiter
kept), CAN as every frame's id and data, the BNO055 as its output registers per poll. Recording a
replay reproduces the replayed bytes exactly (tests/test_replay.py checks the hash).
"""
import sys
import time

import numpy as np

from edge.progress import Progress
from edge.shutdown import StopSignals
from edgetools.sim.session import Session, SerialLog
from firmware_bridge.transports import parse_url


class SerialTap:
    """Raw frames from a serial port, each with the time its delimiter arrived."""

    def __init__(self, port, baud, clock):
        import serial
        self.port = serial.Serial(port, baud, timeout=0)
        self.clock, self.log, self.pending = clock, SerialLog(), b""

    def poll(self):
        chunk = self.port.read(max(1, self.port.in_waiting))
        if not chunk:
            return
        data = self.pending + chunk
        *frames, self.pending = data.split(b"\x00")
        now = self.clock()
        for f in frames:
            self.log.add(now, f + b"\x00")

    def close(self):
        self.port.close()


class CanTap:
    def __init__(self, interface, channel, clock):
        import can
        self.bus = can.Bus(interface=interface, channel=channel)
        self.clock, self.t, self.ids, self.data = clock, [], [], []

    def poll(self):
        while (m := self.bus.recv(timeout=0)) is not None:
            if m.is_error_frame or m.is_remote_frame or m.dlc != 8:
                continue
            self.t.append(self.clock())
            self.ids.append(m.arbitration_id)
            self.data.append(np.frombuffer(bytes(m.data), np.uint8))

    def close(self):
        self.bus.shutdown()


class I2cTap:
    def __init__(self, source, clock):
        self.source, self.clock, self.t, self.q, self.a = source, clock, [], [], []

    def poll(self):
        while (s := self.source.recv(timeout=0)) is not None:
            self.t.append(self.clock())
            self.q.append(s.quat)
            self.a.append(s.accel if s.accel is not None else np.zeros(3))

    def close(self):
        self.source.close()


def open_taps(urls, clock, opener=None):
    from firmware_bridge.transports import open_source
    taps = {}
    for url in urls:
        scheme, netloc, path, query = parse_url(url)
        if scheme == "serial":
            role = query.get("role", "both")
            taps["headset" if role == "headset" else "hub"] = SerialTap(path, int(query.get("baud", 460800)), clock)
        elif scheme == "can":
            taps["can"] = CanTap(netloc, path.lstrip("/"), clock)
        else:
            taps["i2c"] = I2cTap((opener or open_source)(url), clock)
    return taps


def session_from_taps(taps, name, start, clock):
    empty = SerialLog()
    rel = lambda ts: [t - start for t in ts]
    h = taps.get("headset")
    b = taps.get("hub")
    c = taps.get("can")
    i = taps.get("i2c")
    return Session(
        name, 60.0, clock() - start, tuple(k for k in ("serial", "i2c", "can") if k in taps or (k == "serial" and (h or b))),
        SerialLog(rel(h.log.t), h.log.frames) if h else empty, SerialLog(rel(b.log.t), b.log.frames) if b else SerialLog(),
        np.array(rel(c.t)) if c else np.zeros(0), np.array(c.ids if c else [], np.int64),
        np.array(c.data if c else [], np.uint8).reshape(-1, 8),
        np.array(rel(i.t)) if i else np.zeros(0), np.array(i.q if i else []).reshape(-1, 4),
        np.array(i.a if i else []).reshape(-1, 3), None, {"recorded": time.strftime("%Y-%m-%dT%H:%M:%S")})


def record(urls, seconds, clock=time.monotonic, opener=None, name="recording", progress=True, stop=None):
    """The traffic of the transports at `urls` for `seconds`, or until stop() says so, as a Session."""
    taps = open_taps(urls, clock, opener)
    start = clock()
    try:
        with Progress(int(seconds * 10), "record") if progress else _NoBar() as bar:
            while clock() - start < seconds and not (stop and stop()):
                for tap in taps.values():
                    tap.poll()
                time.sleep(0.001)
                bar.n = int((clock() - start) * 10) - 1
                bar.update()
    finally:
        for tap in taps.values():
            tap.close()
    return session_from_taps(taps, name, start, clock)


class _NoBar:
    n = 0

    def update(self, *a, **k):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass


def main(args):
    from firmware_bridge import config as config_mod
    try:
        cfg = config_mod.load(args.config)
    except config_mod.ConfigError as e:
        print(f"edge: {e}", file=sys.stderr)
        return 2
    # SIGTERM or Ctrl-C ends the recording early and keeps what it caught (edge.shutdown)
    with StopSignals() as stop:
        session = record([cfg.headset] + cfg.trackers, args.seconds, name=args.out, stop=stop.requested)
        if stop.requested():
            print(f"edge record: stopped by {stop.signal_name}; saving what was recorded", file=sys.stderr)
        session.save(args.out)
    print(f"wrote {args.out}: {len(session.headset.frames)} headset frames, {len(session.hub.frames)} hub frames, "
          f"{len(session.can_t)} CAN frames, {len(session.i2c_t)} I2C reads", file=sys.stderr)
    return 0
