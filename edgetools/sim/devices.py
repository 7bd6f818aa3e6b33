"""The simulated devices of `edge replay`, each speaking its real protocol over a real OS interface:
serial devices on pty pairs, CAN tracker nodes on python-can's virtual bus, SlimeVR trackers on UDP
sockets on loopback, a hostile datagram flood, and the waist BNO055 as a register-level fake. The
simulator's clock (SimClock) is wall time or one the harness advances.
"""
import fcntl
import os
import socket
import struct
import termios
import time
from pathlib import Path

import can
import numpy as np

from edgetools.sim.bno055_fake import ChipBehaviour, FakeBNO055


class SimClock:
    """Wall time since start (realtime) or a clock the loop advances (max)."""

    def __init__(self, realtime):
        self.realtime, self.t, self.t0 = realtime, 0.0, time.monotonic()

    def __call__(self):
        return time.monotonic() - self.t0 if self.realtime else self.t

    def sleep(self, seconds):
        """What a device driver's wait does: real sleep, or moving simulated time on."""
        if self.realtime:
            time.sleep(seconds)
        else:
            self.t += max(seconds, 0.0)

    def advance_to(self, t):
        if not self.realtime:
            self.t = max(self.t, t)


def pending_bytes(fd):
    """Bytes waiting to be read on a tty descriptor (FIONREAD)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


def wait_readable(slave, sent, timeout=0.5):
    """Until a pty's slave end holds at least `sent` bytes (those just written to its master: the kernel
    hands them over from a work queue, a moment later), or `timeout` passes."""
    give_up = time.monotonic() + timeout
    while pending_bytes(slave) < sent and time.monotonic() < give_up:
        time.sleep(0.0001)


def open_pty_at(path):
    """A pty pair whose slave end a program opens at `path` (a symlink, as udev gives a stable name):
    (master, slave) descriptors."""
    master, slave = os.openpty()
    if os.path.lexists(path):
        os.unlink(path)
    os.symlink(os.ttyname(slave), path)
    return master, slave


def close_pty_at(path, master, slave):
    """Undo open_pty_at: the symlink goes, both ends close."""
    if os.path.islink(path):
        os.unlink(path)
    for fd in (master, slave):
        os.close(fd)


class SerialDevice:
    """A serial device on the master side of a pty; the board sees `path` (a symlink to /dev/pts/N).

    The kernel hands bytes written to a pty master to the slave side from a work queue, a moment later.
    With `settle` (--speed max) emit_until waits until they are readable there, so a simulated tick
    always sees exactly what was sent before it and a replay is the same bytes every time."""

    def __init__(self, name, log, folder, settle=False):
        self.name, self.log, self.path, self.settle = name, log, str(Path(folder) / name), settle
        self.next = 0
        self.master = self.slave = None
        self.plug()

    def plug(self):
        self.master, self.slave = open_pty_at(self.path)

    def unplug(self):
        close_pty_at(self.path, self.master, self.slave)
        self.master = self.slave = None

    def emit_until(self, t):
        sent = 0
        while self.next < len(self.log.t) and self.log.t[self.next] <= t:
            if self.master is not None:
                try:
                    sent += os.write(self.master, self.log.frames[self.next])
                except OSError:
                    pass
            self.next += 1
        if self.settle and sent:
            self.wait_readable(sent)

    def wait_readable(self, sent, timeout=0.5):
        """Until the board's end holds at least the `sent` bytes just written (it drains every tick)."""
        if self.slave is not None:
            wait_readable(self.slave, sent, timeout)

    def close(self):
        if self.master is not None:
            self.unplug()


class CanDevice:
    """CAN tracker nodes on a python-can virtual bus; frames carry the send time as their timestamp."""

    def __init__(self, session, channel, clock):
        self.s, self.clock, self.next = session, clock, 0
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)

    def emit_until(self, t):
        s = self.s
        while self.next < len(s.can_t) and s.can_t[self.next] <= t:
            self.bus.send(can.Message(arbitration_id=int(s.can_id[self.next]), data=bytes(s.can_data[self.next]),
                                      is_extended_id=False, timestamp=self.clock()))
            self.next += 1

    def close(self):
        self.bus.shutdown()


class SlimeVRDevice:
    """One SlimeVR tracker on a UDP socket of its own, on loopback: it broadcasts its handshake (here:
    to the board's address) once a second until the board answers, then sends its recorded datagrams
    on time; a tracker that has heard nothing from the board for 3 s searches again, as the firmware
    does. unplug(seconds) makes it go silent and then restart (a new handshake)."""

    def __init__(self, mac, log, server, clock):
        from firmware_bridge.wire.slimevr import TrackerEncoder
        self.mac, self.log, self.server, self.clock = mac, log, server, clock
        self.enc = TrackerEncoder(mac)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.connected, self.next, self.last_try, self.last_heard, self.silent_until = False, 0, -1e9, 0.0, -1.0
        self.handshakes = 0

    def emit_until(self, t):
        from firmware_bridge.wire.slimevr import HANDSHAKE_REPLY
        while True:                                 # what the board sent
            try:
                data = self.sock.recv(2048)
            except (BlockingIOError, OSError):
                break
            self.last_heard = t
            if data[:13] == HANDSHAKE_REPLY[:13] and not self.connected:
                self.connected = True
                self.sock.sendto(self.enc.sensor_info(0), self.server)    # as the firmware does, until acked
        if t < self.silent_until:                   # unplugged: nothing in, nothing out
            while self.next < len(self.log.t) and self.log.t[self.next] <= t:
                self.next += 1
            return
        if self.connected and t - self.last_heard > 3.0:
            self.connected = False                  # the firmware's TIMEOUT: search for the server again
        if not self.connected:
            if t - self.last_try >= 1.0:
                self.last_try = t
                self.handshakes += 1
                self.sock.sendto(self.enc.handshake(), self.server)
            while self.next < len(self.log.t) and self.log.t[self.next] <= t:
                self.next += 1                      # what it measured meanwhile is not sent
            return
        while self.next < len(self.log.t) and self.log.t[self.next] <= t:
            try:
                self.sock.sendto(self.log.frames[self.next], self.server)
            except OSError:
                pass
            self.next += 1

    def unplug(self, t, seconds):
        """Silent for `seconds` from t, then a fresh start: a new handshake."""
        self.silent_until, self.connected, self.last_try = t + seconds, False, -1e9

    def close(self):
        self.sock.close()


def flood(address, pps, done, seed=7):
    """A hostile device on the network: `pps` datagrams a second of random bytes, truncated and
    bit-flipped SlimeVR packets, at the board's SlimeVR port, until `done` (loopback only)."""
    from firmware_bridge.wire.slimevr import TrackerEncoder
    rng = np.random.default_rng(seed)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    real = TrackerEncoder("02:00:00:00:00:99").rotation(0, np.array([1.0, 0, 0, 0]))
    t0, n = time.perf_counter(), 0
    while not done.is_set():
        kind = n % 3
        if kind == 0:
            data = rng.bytes(int(rng.integers(1, 200)))
        elif kind == 1:
            data = real[:int(rng.integers(0, len(real)))]
        else:
            b = bytearray(real)
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
            data = bytes(b)
        try:
            sock.sendto(data, address)
        except OSError:
            pass
        n += 1
        lag = n / pps - (time.perf_counter() - t0)
        if lag > 0:
            time.sleep(lag)
    sock.close()
    if os.environ.get("EDGEPOSE_FLOOD_LOG"):
        Path(os.environ["EDGEPOSE_FLOOD_LOG"]).write_text(f"{n} {time.perf_counter() - t0}\n")


def bno055_for(session, clock, faults):
    """The waist puck: the fake serves the recorded output registers; outages become bus failures."""
    q, a, rate = session.i2c_quat, session.i2c_accel, 100.0
    valid = np.all(np.isfinite(q), axis=1)
    last_good = np.maximum.accumulate(np.where(valid, np.arange(len(q)), 0))

    def motion(t):
        i = min(int(t * rate), len(q) - 1)
        return q[last_good[i]], a[i]

    chip = FakeBNO055(motion, clock=clock, sleep=clock.sleep, behaviour=ChipBehaviour(
        boot_seconds=0.0, calibration_seconds=(0, 0, 0), error_rate=faults.get("i2c_error_rate", 0.0), seed=1))
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (~valid).astype(int), [0]])))
    for start, end in zip(edges[::2], edges[1::2], strict=True):            # a disconnected puck NACKs
        chip.fail_between(session.i2c_t[start], session.i2c_t[min(end, len(q) - 1)])
    if faults.get("i2c_block_ms"):
        return SlowBus(chip, faults["i2c_block_ms"] / 1000.0, faults.get("i2c_block_every_ms", 200) / 1000.0)
    return chip


class SlowBus:
    """An I2C bus whose block read stalls for `block_s` of real time once every `every_s` (clock
    stretching at a 10 kHz bus clock, a chip re-initialising): the wall clock, whatever the simulated
    one says, so a replay shows what a blocking read does to the tick."""

    def __init__(self, bus, block_s, every_s):
        self.bus, self.block_s, self.every_s = bus, block_s, every_s
        self.next_stall = time.monotonic() + every_s
        self.stalls = 0

    def read_i2c_block_data(self, *args, **kw):
        if time.monotonic() >= self.next_stall:
            time.sleep(self.block_s)
            self.stalls += 1
            self.next_stall = time.monotonic() + self.every_s
        return self.bus.read_i2c_block_data(*args, **kw)

    def __getattr__(self, name):        # every other SMBus method as the chip has it
        return getattr(self.bus, name)
