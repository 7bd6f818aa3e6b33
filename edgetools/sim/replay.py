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

import numpy as np

from edge import native
from edge.inference import DEFAULT_PRECISION
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


def board_config(session, devices, can_channel, samples, lookahead, bvh, adaptive=False, precision=DEFAULT_PRECISION,
                 bench="replay", outputs=None, calibration="", headset_url=None):
    """The board's config for a session: real ptys and CAN, and sim:// sources on the bench devices
    `{bench}-waist` (the BNO055 fake) and `{bench}-slimevr`; `outputs`: more [output] keys (vmc, vrchat,
    vmc_mode, vrchat_trackers); `calibration`: a calibration file (edge calibrate's); `headset_url`: the
    headset link instead of the session's serial headset (webxr://...)."""
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
        "headset": {"url": headset_url or f"serial://{devices['headset'].path}?role=headset"},
        "trackers": trackers,
        "output": {"pose_stream": "headset", **({"bvh": bvh} if bvh else {}), **(outputs or {})},
        "runtime": {"samples": samples, "lookahead": lookahead, "adaptive": adaptive, "precision": precision,
                    **({"calibration": str(calibration)} if calibration else {})},
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


def replay(session, speed="max", samples=16, lookahead=0, seconds=None, faults=None, bvh=None, status=None,
           models=None, adaptive=False, precision=DEFAULT_PRECISION, pose_log=None, threaded=None, outputs=None,
           calibration="", dump=None, headset=None):
    """Returns the report dict; `pose_log` (a binary file) receives the pose stream's raw bytes.
    headset: a live headset instead of the session's serial one (edgetools.sim.quest.QuestHeadset: the
    board's webxr:// page in an emulated Quest playing the same take), with `url`, `prepare(service)`
    (pair it before the session clock starts), `start(clock)` (play from session time 0) and `finish()`
    (read what it shows before the board stops); the poses the board sends it are scored as the serial
    stream's are.
    threaded: reader threads in the service (default: in real time, not at --speed max). outputs:
    [output] keys such as {"vmc": "127.0.0.1:39539", "vrchat": "192.168.1.20:9000"}; calibration: a file.
    dump: a folder for the decoded poses beside the ground truth (edge eval --dump's format)."""
    faults = faults or {}
    # Build the compiled core (first use: seconds of cc) before the clock starts, or a real-time replay
    # begins seconds behind its own devices and the synchroniser starts on a backlog.
    native.load()
    clock = SimClock(realtime=(speed == "realtime"))
    folder = tempfile.mkdtemp(prefix="edgepose-sim-")
    settle = speed != "realtime"
    devices = {} if headset is not None else {"headset": SerialDevice("headset", session.headset, folder, settle)}
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
        cfg = board_config(session, devices, can_channel, samples, lookahead, bvh, adaptive, precision, bench, outputs,
                           calibration, None if headset is None else headset.url)
        if models:
            cfg.models = models
        # Real time: a reader thread per source, as on the board. Max speed: the tick reads the sources
        # itself, so every run sees the same input (tests/test_golden.py).
        service = Service(cfg, clock=clock, status=status, threaded=clock.realtime if threaded is None else threaded)
    except BaseException:
        for dev in list(devices.values()) + ([can_dev] if can_dev else []):
            dev.close()
        for key in (f"{bench}-waist", f"{bench}-slimevr"):
            scheme.BENCH.pop(key, None)
        raise
    opened = [link.url for link in service.links]
    if headset is None:
        ear = Listener(fd=devices["headset"].master, record=pose_log)
    else:
        try:
            tap = tap_pose_stream(service)
            ear = Listener(fd=tap[0], record=pose_log)
            headset.prepare(service)
        except BaseException:
            service.close()
            raise
        clock.t0 = time.monotonic()        # the session starts now that the headset is ready
        headset.start(clock)
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
    if clock.realtime and headset is None:
        # The session starts now, with the service and its readers up: started when the devices were made,
        # the first ticks would be due before the loop began (~0.1 s of start-up) and run late, catching up.
        clock.t0 = time.monotonic()
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
                service.step(step_now, due=now + 1.0 / hz if clock.realtime else None)
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
        while plugged.is_set() and pending_bytes(ear.fd) and time.monotonic() < give_up:
            time.sleep(0.005)
        time.sleep(0.01)
        score(inbox, metrics, ticks_by_us, replug)
        if headset is not None:
            headset.finish()               # what the headset shows and counted, while the board still runs
    finally:
        done.set()
        for f in flooding:
            f.set()
        reader.join(1.0)
        summary = service.summary()
        service.close()
        if headset is not None:
            os.close(tap[0])
            os.close(tap[1])
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
    if dump:
        from pathlib import Path
        from edge.skeleton import JOINT_NAMES, PARENTS
        Path(dump).mkdir(parents=True, exist_ok=True)
        write_dump(Path(dump) / f"{Path(session.name).stem or 'replay'}.npz", metrics, JOINT_NAMES, PARENTS, hz)
    # RSS after the first 10% (imports, pools warmed) against the end: a leak shows as growth.
    warm = rss[max(1, len(rss) // 10)] if len(rss) > 2 else rss[0]
    out["rss_mb"] = {"start": rss[0], "after_warmup": warm, "end": rss[-1], "growth_after_warmup": rss[-1] - warm}
    return out
