"""`edge replay`: play a session through simulated devices into the real board service.

The devices speak the real protocols over real OS interfaces: the headset and the tracker hub sit on
the far end of pty pairs (the board opens a /dev/pts path, through a stable symlink as udev would
give it, with pyserial), the waist BNO055 is a register-level fake behind the smbus2 interface, and the
foot trackers are CAN nodes on python-can's virtual bus. The service under test is `edge run`'s
Service; a host-side Listener decodes the pose stream the board sends back over the headset link.

--speed realtime paces everything on the wall clock; --speed max advances a simulated clock one model
tick at a time (the same bytes, just faster), which is what the tests use.
"""
import fcntl
import json
import os
import socket
import struct
import termios
import sys
import tempfile
import threading
from collections import deque
import time
from pathlib import Path

import can
import numpy as np

from edge import native, quat
from edge.inference import DEFAULT_PRECISION
from edge.skeleton import fk
from firmware_bridge import config as config_mod
from edgetools.listen import Listener
from firmware_bridge.service import Service
from edgetools.sim import scheme
from edgetools.sim.bno055_fake import FakeBNO055
from edgetools.sim.session import FAULTS, CAN_NODES, HUB_IDS, Session, fault_profile, placement, synthesize


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
        self.master, self.slave = os.openpty()
        if os.path.lexists(self.path):
            os.unlink(self.path)
        os.symlink(os.ttyname(self.slave), self.path)

    def unplug(self):
        os.unlink(self.path)
        for fd in (self.master, self.slave):
            os.close(fd)
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
        give_up = time.monotonic() + timeout
        while self.slave is not None and pending_bytes(self.slave) < sent and time.monotonic() < give_up:
            time.sleep(0.0001)

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

    chip = FakeBNO055(motion, clock=clock, sleep=clock.sleep, boot_seconds=0.0, calibration_seconds=(0, 0, 0),
                      error_rate=faults.get("i2c_error_rate", 0.0), seed=1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (~valid).astype(int), [0]])))
    for start, end in zip(edges[::2], edges[1::2]):            # a disconnected puck NACKs
        chip.fail_between(session.i2c_t[start], session.i2c_t[min(end, len(q) - 1)])
    return chip


class StreamMetrics:
    """Decoded-pose metrics kept in preallocated arrays, so a long soak measures the runtime's memory,
    not the harness's: per-frame arrival, latency and error, and a 3-frame window for jerk."""

    def __init__(self, ticks, hz, gt_pos, lookahead):
        self.hz, self.gt, self.lookahead = hz, gt_pos, lookahead
        self.seen = np.zeros(ticks + 2, bool)
        self.latency = np.full(ticks + 2, np.nan)
        self.error = np.full(ticks + 2, np.nan)
        self.t = np.full(ticks + 2, np.nan)
        self.step = np.full(ticks + 2, np.nan)           # the largest joint move from the previous frame (m)
        self.jerk_sum, self.jerk_n, self.decoded = 0.0, 0, 0
        self.window = np.zeros((4, 21, 3))
        self.window_frames = np.full(4, -10)
        self.wall = {}                                   # pipeline frame index -> wall time its tick began

    def add(self, f, arrived, ticks):
        """f: a decoded PoseFrame; ticks: microsecond tick time -> (pipeline frame index, wall time of its tick)."""
        entry = ticks.get(int(round(f.t * 1e6)))
        if entry is None:
            return
        o = entry[0]
        if not 0 <= o < len(self.seen):
            return
        self.decoded += 1
        self.seen[o] = True
        self.t[o] = f.t
        produced = self.wall.get(o + self.lookahead)
        if produced is not None:
            self.latency[o] = (arrived - produced) * 1000
        _, pos = fk(quat.to_matrix(f.rotations), f.root_pos)
        g = int(round(f.t * self.hz))                                   # ground truth is on the session clock
        if self.gt is not None and self.hz <= g < len(self.gt):         # skip the first second, like eval
            self.error[o] = np.linalg.norm(pos - self.gt[g], axis=-1).mean()
        self.window = np.roll(self.window, -1, axis=0)
        self.window_frames = np.roll(self.window_frames, -1)
        self.window[-1], self.window_frames[-1] = pos, o
        if self.window_frames[-2] == o - 1:
            self.step[o] = np.linalg.norm(pos - self.window[-2], axis=-1).max()
        if g >= self.hz and np.all(np.diff(self.window_frames) == 1):
            jerk = (self.window[3] - 3 * self.window[2] + 3 * self.window[1] - self.window[0]) * self.hz ** 3
            self.jerk_sum += np.linalg.norm(jerk, axis=-1).mean()
            self.jerk_n += 1


def score(inbox, metrics, ticks_by_us, replug):
    """Fold decoded frames into the metrics (and note the first frame after a re-plug)."""
    while inbox:
        f, arrived = inbox.popleft()
        metrics.add(f, arrived, ticks_by_us)
        if replug[0] is not None and replug[1] is None and f.t >= replug[0] - 1e-9:
            replug[1] = f.t


def board_config(session, devices, can_channel, samples, lookahead, bvh, adaptive=False, precision=DEFAULT_PRECISION,
                 bench="replay"):
    """The board's config for a session: real ptys and CAN, and sim:// sources on the bench devices
    `{bench}-waist` (the BNO055 fake) and `{bench}-slimevr`."""
    place = session.meta.get("placement") or placement(session.transports)
    pairs = lambda ids, names: ",".join(f"{k}:{v}" for k, v in ids.items() if v in names)
    trackers = []
    if "hub" in devices and place["hub"]:
        trackers.append({"url": f"serial://{devices['hub'].path}?role=hub&trackers={pairs(HUB_IDS, place['hub'])}"})
    if place["i2c"]:
        trackers.append({"url": f"sim://i2c/{bench}-waist?tracker=waist&rate=100"})
    if place["can"]:
        trackers.append({"url": f"can://virtual/{can_channel}?nodes={pairs(CAN_NODES, place['can'])}"})
    if place.get("slimevr"):
        macs = session.meta.get("slimevr_trackers", {})
        trackers.append({"url": f"sim://slimevr/{bench}-slimevr?trackers=" + ",".join(f"{m}/0:{n}" for m, n in macs.items())})
    return config_mod.from_dict({
        "headset": {"url": f"serial://{devices['headset'].path}?role=headset"},
        "trackers": trackers,
        "output": {"pose_stream": "headset", **({"bvh": bvh} if bvh else {})},
        "runtime": {"samples": samples, "lookahead": lookahead, "adaptive": adaptive, "precision": precision},
    }, "replay")


def replay(session, speed="max", samples=16, lookahead=10, seconds=None, faults=None, bvh=None, status=None,
           models=None, adaptive=False, precision=DEFAULT_PRECISION, pose_log=None):
    """Returns the report dict; `pose_log` (a binary file) receives the pose stream's raw bytes."""
    faults = faults or {}
    # Build the compiled core (first use: seconds of cc) before the clock starts, or a real-time replay
    # begins seconds behind its own devices and the synchroniser starts on a backlog.
    native.load()
    clock = SimClock(realtime=(speed == "realtime"))
    folder = tempfile.mkdtemp(prefix="edgepose-sim-")
    settle = speed != "realtime"
    devices = {"headset": SerialDevice("headset", session.headset, folder, settle)}
    if session.hub.frames:
        devices["hub"] = SerialDevice("hub", session.hub, folder, settle)
    can_channel = f"edgepose-{os.getpid()}-{id(session)}"
    can_dev = CanDevice(session, can_channel, clock) if "can" in session.transports and len(session.can_t) else None
    chip = bno055_for(session, clock, faults) if len(session.i2c_t) else None
    errors, slimevr_devices, flooding = [], [], []

    def slimevr_opened(source):
        """The simulated trackers talk to the port the board's SlimeVR source got."""
        slimevr_devices[:] = [SlimeVRDevice(mac, log, source.address, clock) for mac, log in session.slimevr.items()]
        if faults.get("slimevr_flood_pps"):        # a process of its own: the board's, not the flood's, GIL
            import multiprocessing as mp
            ctx = mp.get_context("fork")
            flooding.append(ctx.Event())
            ctx.Process(target=flood, args=(source.address, faults["slimevr_flood_pps"], flooding[0]),
                        daemon=True).start()

    bench = f"replay{os.getpid()}-{id(session)}"
    scheme.BENCH[f"{bench}-waist"] = scheme.BenchDevice(chip, clock, clock.sleep)
    scheme.BENCH[f"{bench}-slimevr"] = scheme.BenchDevice(None, clock, clock.sleep, slimevr_opened)
    try:
        cfg = board_config(session, devices, can_channel, samples, lookahead, bvh, adaptive, precision, bench)
        if models:
            cfg.models = models
        service = Service(cfg, clock=clock, status=status)
    except BaseException:
        for dev in list(devices.values()) + ([can_dev] if can_dev else []):
            dev.close()
        for key in (f"{bench}-waist", f"{bench}-slimevr"):
            scheme.BENCH.pop(key, None)
        raise
    opened = [link.url for link in service.links]
    ear = Listener(fd=devices["headset"].master, record=pose_log)
    hz, duration = cfg.hz, session.duration if seconds is None else min(seconds, session.duration)
    ticks = int(duration * hz)
    metrics = StreamMetrics(ticks, hz, session.gt_pos, service.pipeline.lookahead)
    ticks_by_us = {}
    inbox = deque()
    plugged = threading.Event()
    plugged.set()
    done = threading.Event()
    replug = [None, None]                           # replug time, first frame of input after it

    def host_reader():
        """The host side reads continuously, as a separate program would."""
        while not done.is_set():
            if not plugged.is_set():
                time.sleep(0.001)
                continue
            try:
                frames = ear.poll(0.002)
            except (OSError, ValueError):           # the pty went away under us (unplug)
                continue
            now = time.perf_counter()
            inbox.extend((f, now) for f in frames)       # scored by the main loop, off the latency path

    reader = threading.Thread(target=host_reader, daemon=True)
    reader.start()
    unplug = (faults.get("unplug_at", np.inf), faults.get("unplug_at", np.inf) + faults.get("unplug_s", 0))
    last_status = 0.0
    rss = [rss_mb()]
    try:
        for k in range(1, ticks + 1):
            now = k / hz
            if clock.realtime:
                delay = now - clock()
                while delay > 0:            # SlimeVR trackers send when they measure, not at our ticks
                    time.sleep(min(delay, 0.002) if slimevr_devices else delay)
                    for dev in slimevr_devices:
                        dev.emit_until(clock())
                    delay = now - clock()
            else:
                clock.advance_to(now)
            if plugged.is_set() and unplug[0] <= now < unplug[1]:
                plugged.clear()
                time.sleep(0.005)                   # let the reader leave the fd before it closes
                devices["headset"].unplug()
            elif not plugged.is_set() and now >= unplug[1]:
                devices["headset"].plug()
                ear.fd = devices["headset"].master
                plugged.set()
                replug[0] = now
            for dev in devices.values():
                dev.emit_until(now)
            for dev in slimevr_devices:
                if faults.get("tracker_unplug") == "slimevr" and dev is slimevr_devices[-1] and \
                        dev.silent_until < 0 and now >= faults.get("tracker_unplug_at", np.inf):
                    dev.unplug(now, faults.get("tracker_unplug_s", 2.0))
                dev.emit_until(now)
            if can_dev:
                can_dev.emit_until(now)
            step_now, index, wall = clock(), service.pipeline.t + 1, time.perf_counter()
            ticks_by_us[int(round(step_now * 1e6))] = (index, wall)
            metrics.wall[index] = wall
            metrics.wall.pop(index - 300, None)                 # both maps stay bounded
            if len(ticks_by_us) > 600:
                ticks_by_us.pop(next(iter(ticks_by_us)))
            try:
                service.step(step_now)
            except Exception as e:          # the run goes on; the report says what broke
                errors.append(f"tick {k}: {type(e).__name__}: {e}")
            if not clock.realtime:
                time.sleep(0.0002)          # give the host reader a moment, as real time would
            score(inbox, metrics, ticks_by_us, replug)
            if now - last_status >= 0.5:
                if status is not None:
                    service.show_status()
                last_status = now
                rss.append(rss_mb())
        time.sleep(0.05)
        give_up = time.monotonic() + 1.0               # the host reads what the board sent last
        while plugged.is_set() and pending_bytes(devices["headset"].master) and time.monotonic() < give_up:
            time.sleep(0.005)
        time.sleep(0.01)
        score(inbox, metrics, ticks_by_us, replug)
    finally:
        done.set()
        for f in flooding:
            f.set()
        reader.join(1.0)
        summary = service.summary()
        service.close()
        if can_dev:
            can_dev.close()
        for dev in list(devices.values()) + slimevr_devices:
            dev.close()
        for key in (f"{bench}-waist", f"{bench}-slimevr"):
            scheme.BENCH.pop(key, None)
        try:
            os.rmdir(folder)
        except OSError:
            pass
    out = report(session, summary, metrics, service, ear, opened, errors, faults, speed, duration,
                 (replug[1] - replug[0]) if replug[1] is not None else None)
    # RSS after the first 10% (imports, pools warmed) against the end: a leak shows as growth.
    warm = rss[max(1, len(rss) // 10)] if len(rss) > 2 else rss[0]
    out["rss_mb"] = {"start": rss[0], "after_warmup": warm, "end": rss[-1], "growth_after_warmup": rss[-1] - warm}
    return out


def report(session, summary, m, service, ear, opened, errors, faults, speed, duration, resume_s):
    hz = service.cfg.hz
    lat = m.latency[np.isfinite(m.latency)]
    lat = lat if len(lat) else np.zeros(1)
    seen = np.flatnonzero(m.seen)
    out = {
        "source": session.name, "speed": speed, "seconds": duration, "faults": faults,
        "trackers": list(service.sync.trackers), "placement": session.meta.get("placement"),
        "slimevr": summary.get("slimevr", {}),
        "trackers_used_by_model": [n for n, _ in service._imu_slots] if service.pipeline.imus else [],
        "frames_in": summary["frames_in"], "frames_out": summary["frames_out"], "poses_decoded": m.decoded,
        "packets_corrupt": int(summary["packets_corrupt"] + ear.stats["corrupt"]),
        "packets_lost": int(summary["packets_lost"] + ear.stats.get("missed", 0)),
        "packets_unknown": int(summary.get("packets_unknown", 0)),
        "tracker_lost_events": summary["tracker_lost_events"], "deadline_misses": summary["deadline_misses"],
        "latency_ms": {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())},
        "latency_note": "wall time from the start of the tick that produced a pose to its decoding by the host "
                        "reader (processing, serial transfer, decoding); the deliberate delays (SSI look-ahead, and the "
                        "synchroniser interpolating one headset period back) are reported apart",
        "lookahead_ms": 1000.0 * service.pipeline.lookahead / hz,
        "sync_delay_ms": 1000.0 * service.cfg.sync_latency, "ssi_switches": service.pipeline.switch_count,
        "samples": service.pipeline.samples, "samples_max": summary["samples_max"], "precision": service.cfg.precision,
        "samples_changes": summary["samples_changes"], "frame_ms": summary["frame_ms"], "reopens": summary["reopens"],
        "output_errors": summary["output_errors"], "resume_after_replug_s": resume_s,
        "devices_down_at_start": summary.get("start_errors", {}),
        "missing_output_frames": int(len(seen) and (seen[-1] - seen[0] + 1 - len(seen))),
        "transports": {"opened": sorted(set(opened))}, "errors": errors,
        "latency_ms_samples": [round(float(x), 3) for x in lat[:20000]],
        "health_timeline": health_timeline(service.health_changes, duration, faults),
    }
    if faults.get("tracker_unplug") == "slimevr":      # a SlimeVR tracker silent, then re-handshaking
        macs = session.meta.get("slimevr_trackers", {})
        name = list(macs.values())[-1] if macs else None
        back_at = faults.get("tracker_unplug_at", 0) + faults.get("tracker_unplug_s", 2.0)
        back = [t for t, src, lost in service.health_changes if src == name and not lost and t >= back_at]
        out["slimevr_restart"] = {"tracker": name, "silent_from_s": faults.get("tracker_unplug_at"),
                                  "restarts_at_s": back_at, "in_use_again_after_s": (back[0] - back_at) if back else None}
    if "tracker_unplug_at" in faults:       # the pose around an extra IMU's loss: no pop
        at, ok = faults["tracker_unplug_at"], np.isfinite(m.step)
        before = m.step[ok & (m.t >= at - 1) & (m.t < at)]
        after = m.step[ok & (m.t >= at) & (m.t < at + 1)]
        if len(before) and len(after):
            out["tracker_unplug"] = {"tracker": faults.get("tracker_unplug"), "at_s": at,
                                     "largest_step_before_m": float(before.max()), "largest_step_after_m": float(after.max()),
                                     "ratio": float(after.max() / before.max())}
    err = m.error[np.isfinite(m.error)]
    if len(err):
        out["mpjpe_cm"] = float(err.mean() * 100)
    if m.jerk_n:
        out["jitter_m_s3"] = m.jerk_sum / m.jerk_n
    return out


def health_timeline(changes, duration, faults, step=0.1):
    """Lost flags per source on a 10 Hz grid, and the injected faults, in the format viz draws."""
    t = np.arange(0.0, duration, step)
    lost = {}
    for when, name, is_lost in changes:
        flags = lost.setdefault(name, np.zeros(len(t), np.int8))
        flags[t >= when] = 1 if is_lost else 0
    marks = [(k, faults.get(f"{k}_at")) for k in ("unplug", "busoff", "clock_jump")]
    return {"t": [round(x, 3) for x in t], "lost": {k: v.tolist() for k, v in lost.items()},
            "faults": [{"t": at, "kind": k.replace("_", "-")} for k, at in marks if at is not None]}


def tile_take(take, seconds):
    """Repeat a take until it lasts `seconds` (for soaks); the body jumps back at each seam."""
    from edge.signals import Signals
    reps = int(np.ceil(seconds * take.fps / take.frames))
    if reps <= 1:
        return take
    sig = take.signals
    from dataclasses import fields
    tiled = Signals(**{f.name: np.concatenate([getattr(sig, f.name)] * reps) for f in fields(sig)})
    imu = {k: np.concatenate([v] * reps) for k, v in (take.imu or {}).items()}
    return type(take)(take.name, tiled, np.concatenate([take.gt_pos] * reps), take.fps, imu)


# Faults the simulated devices apply while replaying; the others shape the traffic when a session is
# synthesised from a take, so a recording cannot have them.
REPLAY_TIME_FAULTS = {"unplug_at", "unplug_s", "i2c_error_rate"}


def load_source(source, transports, faults, seed=0, seconds=None, trackers=None):
    """A recording (.npz session), or a BVH clip / sample take synthesised through the device models
    (repeated to last `seconds` when that is longer than the take) with the extra IMUs `trackers`
    (default: the two CAN foot trackers). A recording carries the trackers it was made with."""
    path = str(source)
    if path.endswith(".npz"):
        d = np.load(path, allow_pickle=False)
        if "kind" in d.files:
            ignored = sorted(set(faults or {}) - REPLAY_TIME_FAULTS)
            if ignored:
                profiles = sorted({name for name, params in FAULTS.items() if set(params) & set(ignored)})
                take = path.replace(".session.npz", ".npz") if path.endswith(".session.npz") else "a take or BVH clip"
                print(f"edge replay: {path} is a recording, replayed as recorded: the fault profile(s) "
                      f"{', '.join(profiles) or ', '.join(ignored)} shape traffic as it is synthesised and do not apply "
                      f"to it (unplug and i2c-errors do). To inject them, replay {take}", file=sys.stderr)
            session = Session.load(path)
            if trackers is not None and tuple(trackers) != tuple(session.meta.get("trackers", ["waist"])[1:]):
                print(f"edge replay: {path} is a recording made with trackers "
                      f"{','.join(session.meta.get('trackers', ['waist']))}; --trackers applies to a take or BVH clip "
                      f"(e.g. samples/cmu_09_12_walk.npz)", file=sys.stderr)
            return session
    from edgetools.takes import load_take
    take = load_take(path)
    if seconds:
        take = tile_take(take, seconds)
    return synthesize(take, transports, faults, seed, trackers=trackers)


def rss_mb():
    with open(f"/proc/{os.getpid()}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0


def main(args):
    try:
        faults = fault_profile(args.faults)
    except ValueError as e:
        print(f"edge replay: {e}", file=sys.stderr)
        return 2
    transports = tuple(args.transport.split(","))
    bad = set(transports) - {"serial", "i2c", "can", "slimevr"}
    if bad:
        print(f"edge replay: unknown transport {sorted(bad)[0]!r}; use serial, i2c, can, slimevr", file=sys.stderr)
        return 2
    try:
        from edge.imus import parse_set
        trackers = None if args.trackers is None else parse_set(args.trackers)
        session = load_source(args.source, transports, faults, seconds=args.seconds, trackers=trackers)
    except (OSError, ValueError) as e:
        print(f"edge replay: cannot use {args.source}: {e}", file=sys.stderr)
        return 2
    samples = 32 if args.samples == "auto" else int(args.samples)
    pose_log = open(args.pose_log, "wb") if getattr(args, "pose_log", None) else None
    try:
        result = replay(session, args.speed, samples, args.lookahead, args.seconds, faults, args.bvh, sys.stderr,
                        args.models, adaptive=args.adaptive or args.samples == "auto", precision=args.precision,
                        pose_log=pose_log)
    finally:
        if pose_log is not None:
            pose_log.close()
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("frames_in", "frames_out", "poses_decoded", "packets_corrupt", "packets_lost", "tracker_lost_events",
            "deadline_misses", "ssi_switches", "mpjpe_cm", "jitter_m_s3")
    print("\n" + "  ".join(f"{k}={result[k]:.4g}" if isinstance(result.get(k), float) else f"{k}={result.get(k)}"
                           for k in keys), file=sys.stderr)
    print(f"latency p50 {result['latency_ms']['p50']:.2f} ms p99 {result['latency_ms']['p99']:.2f} ms "
          f"(+ look-ahead {result['lookahead_ms']:.0f} ms); wrote {args.json}" + (f" and {args.bvh}" if args.bvh else ""),
          file=sys.stderr)
    if result["errors"]:        # the run went on, but something broke: say so in the exit code
        print(f"edge replay: {len(result['errors'])} error(s), the first: {result['errors'][0]}", file=sys.stderr)
        return 1
    return 0
