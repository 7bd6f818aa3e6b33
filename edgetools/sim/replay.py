"""`edge replay`'s harness: play a session through simulated devices into the real board service.

The devices speak the real protocols over real OS interfaces: the headset and the tracker hub sit on
the far end of pty pairs (the board opens a /dev/pts path, through a stable symlink as udev would
give it, with pyserial), the waist BNO055 is a register-level fake behind the smbus2 interface, and the
foot trackers are CAN nodes on python-can's virtual bus. The service under test is `edge run`'s
Service; a host-side Listener decodes the pose stream the board sends back over the headset link.

--speed realtime paces everything on the wall clock; --speed max advances a simulated clock one model
tick at a time (the same bytes, just faster), which is what the tests use. The devices are
edgetools.sim.devices, the host's measurements stream_metrics, the report replay_report, what to
play sources, and the command replay_cli.
"""
import os
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from edge import native
from edge.skeleton import JOINT_NAMES, PARENTS
from edgetools.listen import Listener
from edgetools.sim import scheme
from edgetools.sim.devices import (CanDevice, SerialDevice, SimClock, SlimeVRDevice, bno055_for, flood,
                                   pending_bytes)
from edgetools.sim.replay_report import report, rss_mb
from edgetools.sim.session import CAN_NODES, HUB_IDS, placement
from edgetools.sim.stream_metrics import StreamMetrics, score, write_dump
from firmware_bridge import config as config_mod
from firmware_bridge.service import Service
from firmware_bridge.wire.messages import encode_pose_frame


def board_config(session, devices, can_channel, runtime=None, output=None, bench="replay", headset_url=None):
    """The board's config for a session: real ptys and CAN, and sim:// sources on the bench devices
    `{bench}-waist` (the BNO055 fake) and `{bench}-slimevr`. `runtime` and `output` are the config file's
    [runtime] and [output] sections (samples, lookahead, adaptive, precision, models, calibration; bvh,
    vmc, vrchat, ...), over the replay's defaults (N=16, no adaptive N); `headset_url`: the headset link
    instead of the session's serial headset (webxr://...)."""
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
    runtime = {k: v for k, v in (runtime or {}).items() if v not in (None, "")}
    return config_mod.from_dict({
        "headset": {"url": headset_url or f"serial://{devices['headset'].path}?role=headset"},
        "trackers": trackers,
        "output": {"pose_stream": "headset", **{k: v for k, v in (output or {}).items() if v}},
        "runtime": {**REPLAY_RUNTIME, **runtime},
    }, "replay")


def tap_pose_stream(service):
    """The poses the board sends a live headset, also written as the serial pose stream to a pipe (its
    read end returned) for the host's metrics: the socket's far end is a browser, not a pty to read."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    source, counter = service.headset.source, [0]
    send = source.send_pose

    def send_and_tap(frame):
        sent = send(frame)
        try:
            os.write(write_fd, encode_pose_frame(frame, counter[0]))
        except BlockingIOError:             # the host reader fell 64 KB behind: it counts the gap
            pass
        counter[0] = (counter[0] + 1) & 0xFFFF
        return sent
    source.send_pose = send_and_tap
    return read_fd, write_fd


REPLAY_RUNTIME = {"samples": 16, "adaptive": False}     # [runtime] a replay starts from (the board's: adaptive)


def replay(session, speed="max", seconds=None, *, runtime=None, output=None, faults=None, status=None,
           pose_log=None, threaded=None, dump=None, headset=None):
    """Play `session` through simulated devices into a board service; returns the report dict.

    runtime, output: the board config's [runtime] and [output] sections (board_config). faults: the
    fault profile (edgetools.sim.session). status: where the service's status line goes. pose_log (a
    binary file) receives the pose stream's raw bytes. threaded: reader threads in the service (default:
    in real time, not at --speed max). dump: a folder for the decoded poses beside the ground truth
    (edge eval --dump's format).
    headset: a live headset instead of the session's serial one (edgetools.sim.quest.QuestHeadset: the
    board's webxr:// page in an emulated Quest playing the same take), with `url`, `prepare(service)`
    (pair it before the session clock starts), `start(clock)` (play from session time 0) and `finish()`
    (read what it shows before the board stops); the poses the board sends it are scored as the serial
    stream's are."""
    bench = ReplayBench(session, speed, faults or {}, headset)
    try:
        service = bench.open_service(runtime, output, status, threaded)
        bench.open_host(pose_log)
        hz = service.cfg.hz
        duration = session.duration if seconds is None else min(seconds, session.duration)
        bench.run(int(duration * hz), hz, status)
        summary = service.summary()
    finally:
        bench.close()
    replug = bench.replug
    out = report(session, summary, bench.metrics, service, bench.ear, bench.opened, bench.errors, bench.faults,
                 speed, duration, (replug[1] - replug[0]) if replug[1] is not None else None)
    if dump:
        Path(dump).mkdir(parents=True, exist_ok=True)
        write_dump(Path(dump) / f"{Path(session.name).stem or 'replay'}.npz", bench.metrics, JOINT_NAMES, PARENTS, hz)
    # RSS after the first 10% (imports, pools warmed) against the end: a leak shows as growth.
    rss = bench.rss
    warm = rss[max(1, len(rss) // 10)] if len(rss) > 2 else rss[0]
    out["rss_mb"] = {"start": rss[0], "after_warmup": warm, "end": rss[-1], "growth_after_warmup": rss[-1] - warm}
    return out


class ReplayBench:
    """The simulated devices around one board service, the host reading its pose stream, and the
    loop that ticks them together. close() undoes whatever was set up, however far it got."""

    def __init__(self, session, speed, faults, headset=None):
        self.session, self.faults, self.headset = session, faults, headset
        # Build the compiled core (first use: seconds of cc) before the clock starts, or a real-time replay
        # begins seconds behind its own devices and the synchroniser starts on a backlog.
        native.load()
        self.clock = SimClock(realtime=(speed == "realtime"))
        self.folder = tempfile.mkdtemp(prefix="edgepose-sim-")
        self.service = self.ear = self.tap = self.metrics = None
        self.errors, self.slimevr_devices, self.flooding, self.opened = [], [], [], []
        self.replug = [None, None]                  # replug time, first frame of input after it
        self.rss = [rss_mb()]
        self.name = f"replay{os.getpid()}-{id(session)}"
        settle = speed != "realtime"
        self.devices = {} if headset is not None else {"headset": SerialDevice("headset", session.headset, self.folder, settle)}
        if session.hub.frames:
            self.devices["hub"] = SerialDevice("hub", session.hub, self.folder, settle)
        self.can_channel = f"edgepose-{os.getpid()}-{id(session)}"
        self.can_dev = (CanDevice(session, self.can_channel, self.clock)
                        if "can" in session.transports and len(session.can_t) else None)
        chip = bno055_for(session, self.clock, faults) if len(session.i2c_t) else None
        scheme.BENCH[f"{self.name}-waist"] = scheme.BenchDevice(chip, self.clock, self.clock.sleep)
        scheme.BENCH[f"{self.name}-slimevr"] = scheme.BenchDevice(None, self.clock, self.clock.sleep, self._slimevr_opened)
        self._done = threading.Event()
        self._plugged = threading.Event()
        self._plugged.set()
        self._reader = None

    def _slimevr_opened(self, source):
        """The simulated trackers talk to the port the board's SlimeVR source got."""
        clock, pps = self.clock, self.faults.get("slimevr_flood_pps")
        self.slimevr_devices[:] = [SlimeVRDevice(mac, log, source.address, clock) for mac, log in self.session.slimevr.items()]
        if pps:        # a process of its own: the board's, not the flood's, GIL
            import multiprocessing as mp
            ctx = mp.get_context("fork")
            self.flooding.append(ctx.Event())
            ctx.Process(target=flood, args=(source.address, pps, self.flooding[0]), daemon=True).start()

    def open_service(self, runtime, output, status, threaded):
        cfg = board_config(self.session, self.devices, self.can_channel, runtime, output, self.name,
                           None if self.headset is None else self.headset.url)
        # Real time: a reader thread per source, as on the board. Max speed: the tick reads the sources
        # itself, so every run sees the same input (tests/test_golden.py).
        self.service = Service(cfg, clock=self.clock, status=status,
                               threaded=self.clock.realtime if threaded is None else threaded)
        self.opened = [link.url for link in self.service.links]
        return self.service

    def open_host(self, pose_log):
        """The host's Listener on the pose stream (the headset pty, or a tap of what a live headset gets),
        and its reader thread; a live headset is paired and started, and starts the session clock."""
        if self.headset is None:
            self.ear = Listener(fd=self.devices["headset"].master, record=pose_log)
        else:
            self.tap = tap_pose_stream(self.service)
            self.ear = Listener(fd=self.tap[0], record=pose_log)
            self.headset.prepare(self.service)
            self.clock.t0 = time.monotonic()        # the session starts now that the headset is ready
            self.headset.start(self.clock)
        self.inbox = deque()
        self._reader = threading.Thread(target=self._host_reader, daemon=True)
        self._reader.start()

    def _host_reader(self):
        """The host side reads continuously, as a separate program would."""
        while not self._done.is_set():
            if not self._plugged.is_set():
                time.sleep(0.001)
                continue
            try:
                frames = self.ear.poll(0.002)
            except (OSError, ValueError):           # the pty went away under us (unplug)
                continue
            now = time.perf_counter()
            self.inbox.extend((f, now) for f in frames)       # scored by the main loop, off the latency path

    def run(self, ticks, hz, status):
        """`ticks` board ticks at `hz`, the devices sending what falls due before each; then the host
        reads what the board sent last."""
        self.metrics = StreamMetrics(ticks, hz, self.session.gt_pos, self.service.pipeline.lookahead)
        self._ticks_by_us = {}
        last_status = 0.0
        if self.clock.realtime and self.headset is None:
            # The session starts now, with the service and its readers up: started when the devices were made,
            # the first ticks would be due before the loop began (~0.1 s of start-up) and run late, catching up.
            self.clock.t0 = time.monotonic()
        for k in range(1, ticks + 1):
            now = k / hz
            self._wait_until(now)
            self._plug_or_unplug(now)
            self._devices_emit(now)
            self._tick(k, now, hz)
            if now - last_status >= 0.5:
                if status is not None:
                    self.service.show_status()
                last_status = now
                self.rss.append(rss_mb())
        self._drain()

    def _wait_until(self, now):
        if not self.clock.realtime:
            self.clock.advance_to(now)
            return
        delay = now - self.clock()
        while delay > 0:            # SlimeVR trackers send when they measure, not at our ticks
            time.sleep(min(delay, 0.002) if self.slimevr_devices else delay)
            for dev in self.slimevr_devices:
                dev.emit_until(self.clock())
            delay = now - self.clock()

    def _plug_or_unplug(self, now):
        """The "unplug" fault: the headset's serial link goes away at unplug_at for unplug_s."""
        start = self.faults.get("unplug_at", np.inf)
        end = start + self.faults.get("unplug_s", 0)
        if self._plugged.is_set() and start <= now < end:
            self._plugged.clear()
            time.sleep(0.005)                   # let the reader leave the fd before it closes
            self.devices["headset"].unplug()
        elif not self._plugged.is_set() and now >= end:
            self.devices["headset"].plug()
            self.ear.fd = self.devices["headset"].master
            self._plugged.set()
            self.replug[0] = now

    def _devices_emit(self, now):
        f = self.faults
        for dev in self.devices.values():
            dev.emit_until(now)
        for dev in self.slimevr_devices:
            if f.get("tracker_unplug") == "slimevr" and dev is self.slimevr_devices[-1] and \
                    dev.silent_until < 0 and now >= f.get("tracker_unplug_at", np.inf):
                dev.unplug(now, f.get("tracker_unplug_s", 2.0))
            dev.emit_until(now)
        if self.can_dev:
            self.can_dev.emit_until(now)

    def _tick(self, k, now, hz):
        """One board tick, remembered by its clock time so the host can match the frame it sends."""
        service, metrics, by_us = self.service, self.metrics, self._ticks_by_us
        step_now, index, wall = self.clock(), service.pipeline.t + 1, time.perf_counter()
        by_us[int(round(step_now * 1e6))] = (index, wall)
        metrics.wall[index] = wall
        metrics.wall.pop(index - 300, None)                 # both maps stay bounded
        if len(by_us) > 600:
            by_us.pop(next(iter(by_us)))
        try:
            service.step(step_now, due=now + 1.0 / hz if self.clock.realtime else None)
        except Exception as e:          # the run goes on; the report says what broke
            self.errors.append(f"tick {k}: {type(e).__name__}: {e}")
        if not self.clock.realtime:
            time.sleep(0.0002)          # give the host reader a moment, as real time would
        score(self.inbox, metrics, by_us, self.replug)

    def _drain(self):
        time.sleep(0.05)
        give_up = time.monotonic() + 1.0               # the host reads what the board sent last
        while self._plugged.is_set() and pending_bytes(self.ear.fd) and time.monotonic() < give_up:
            time.sleep(0.005)
        time.sleep(0.01)
        score(self.inbox, self.metrics, self._ticks_by_us, self.replug)
        if self.headset is not None:
            self.headset.finish()               # what the headset shows and counted, while the board still runs

    def close(self):
        self._done.set()
        for f in self.flooding:
            f.set()
        if self._reader is not None:
            self._reader.join(1.0)
        if self.service is not None:
            self.service.close()
        for fd in self.tap or ():
            os.close(fd)
        for dev in list(self.devices.values()) + self.slimevr_devices + ([self.can_dev] if self.can_dev else []):
            dev.close()
        for key in (f"{self.name}-waist", f"{self.name}-slimevr"):
            scheme.BENCH.pop(key, None)
        try:
            os.rmdir(self.folder)
        except OSError:
            pass
