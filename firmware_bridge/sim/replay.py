"""`edge replay`: play a session through simulated devices into the real board service.

The devices speak the real protocols over real OS interfaces: the headset and the tracker hub sit on
the far end of pty pairs (the board opens a /dev/pts path, through a stable symlink as udev would
give it, with pyserial), the waist BNO055 is a register-level fake behind the smbus2 interface, and the
foot trackers are CAN nodes on python-can's virtual bus. The service under test is `edge run`'s
Service; a host-side Listener decodes the pose stream the board sends back over the headset link.

--speed realtime paces everything on the wall clock; --speed max advances a simulated clock one model
tick at a time (the same bytes, just faster), which is what the tests use.
"""
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import numpy as np

from edge import quat
from edge.skeleton import fk
from firmware_bridge import config as config_mod
from firmware_bridge.listen import Listener
from firmware_bridge.service import Service, open_configured
from firmware_bridge.sim.bno055_fake import FakeBNO055
from firmware_bridge.sim.session import CAN_NODES, HUB_IDS, Session, fault_profile, placement, synthesize
from firmware_bridge.transports import open_source


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


class SerialDevice:
    """A serial device on the master side of a pty; the board sees `path` (a symlink to /dev/pts/N)."""

    def __init__(self, name, log, folder):
        self.name, self.log, self.path = name, log, str(Path(folder) / name)
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
        while self.next < len(self.log.t) and self.log.t[self.next] <= t:
            if self.master is not None:
                try:
                    os.write(self.master, self.log.frames[self.next])
                except OSError:
                    pass
            self.next += 1

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


def board_config(session, devices, can_channel, samples, lookahead, bvh):
    place = session.meta.get("placement") or placement(session.transports)
    pairs = lambda ids, names: ",".join(f"{k}:{v}" for k, v in ids.items() if v in names)
    trackers = []
    if "hub" in devices and place["hub"]:
        trackers.append({"url": f"serial://{devices['hub'].path}?role=hub&trackers={pairs(HUB_IDS, place['hub'])}"})
    if place["i2c"]:
        trackers.append({"url": "i2c://1/0x28?tracker=waist&rate=100"})
    if place["can"]:
        trackers.append({"url": f"can://virtual/{can_channel}?nodes={pairs(CAN_NODES, place['can'])}"})
    return config_mod.from_dict({
        "headset": {"url": f"serial://{devices['headset'].path}?role=headset"},
        "trackers": trackers,
        "output": {"pose_stream": "headset", **({"bvh": bvh} if bvh else {})},
        "runtime": {"samples": samples, "lookahead": lookahead},
    }, "replay")


def replay(session, speed="max", samples=16, lookahead=10, seconds=None, faults=None, bvh=None, status=None,
           models=None):
    faults = faults or {}
    clock = SimClock(realtime=(speed == "realtime"))
    folder = tempfile.mkdtemp(prefix="edgepose-sim-")
    devices = {"headset": SerialDevice("headset", session.headset, folder)}
    if session.hub.frames:
        devices["hub"] = SerialDevice("hub", session.hub, folder)
    can_channel = f"edgepose-{os.getpid()}-{id(session)}"
    can_dev = CanDevice(session, can_channel, clock) if "can" in session.transports and len(session.can_t) else None
    chip = bno055_for(session, clock, faults) if len(session.i2c_t) else None
    opened, errors = [], []

    def opener(url):
        opened.append(url)
        if url.startswith("i2c://"):
            return open_source(url, bus=chip, clock=clock, sleep=clock.sleep)
        return open_configured(url)

    try:
        cfg = board_config(session, devices, can_channel, samples, lookahead, bvh)
        if models:
            cfg.models = models
        service = Service(cfg, clock=clock, status=status, opener=opener)
    except BaseException:
        for dev in list(devices.values()) + ([can_dev] if can_dev else []):
            dev.close()
        raise
    ear = Listener(fd=devices["headset"].master)
    hz, duration = cfg.hz, session.duration if seconds is None else min(seconds, session.duration)
    arrivals, tick_wall = [], {}
    plugged = threading.Event()
    plugged.set()
    done = threading.Event()

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
            arrivals.extend((f, now) for f in frames)

    reader = threading.Thread(target=host_reader, daemon=True)
    reader.start()
    unplug = (faults.get("unplug_at", np.inf), faults.get("unplug_at", np.inf) + faults.get("unplug_s", 0))
    replug_t = None
    ticks = int(duration * hz)
    last_status = 0.0
    try:
        for k in range(1, ticks + 1):
            now = k / hz
            if clock.realtime:
                delay = now - clock()
                if delay > 0:
                    time.sleep(delay)
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
                replug_t = now
            for dev in devices.values():
                dev.emit_until(now)
            if can_dev:
                can_dev.emit_until(now)
            tick_wall[service.pipeline.t + 1] = time.perf_counter()
            try:
                service.step(clock())
            except Exception as e:          # the run goes on; the report says what broke
                errors.append(f"tick {k}: {type(e).__name__}: {e}")
            if not clock.realtime:
                time.sleep(0.0002)          # give the host reader a moment, as real time would
            if status is not None and now - last_status >= 0.5:
                service.show_status()
                last_status = now
        time.sleep(0.05)
    finally:
        done.set()
        reader.join(1.0)
        summary = service.summary()
        service.close()
        if can_dev:
            can_dev.close()
        for dev in devices.values():
            dev.close()
        try:
            os.rmdir(folder)
        except OSError:
            pass
    decoded, latency, resumed_t = [], [], None
    for f, at in arrivals:
        decoded.append(f)
        produced = tick_wall.get(int(round(f.t * hz)) - 1 + service.pipeline.lookahead)
        if produced is not None:
            latency.append((at - produced) * 1000)
        if replug_t is not None and resumed_t is None and f.t >= replug_t - 1e-9:
            resumed_t = f.t
    return report(session, summary, decoded, latency, service, ear, opened, errors, faults, speed, duration,
                  (resumed_t - replug_t) if resumed_t is not None else None)


def decoded_positions(frames):
    rot = quat.to_matrix(np.array([f.rotations for f in frames]))
    _, pos = fk(rot, np.array([f.root_pos for f in frames]))
    return pos


def report(session, summary, decoded, latency, service, ear, opened, errors, faults, speed, duration, resume_s):
    hz = service.cfg.hz
    lat = np.array(latency) if latency else np.zeros(1)
    corrupt = summary["packets_corrupt"] + ear.stats["corrupt"]
    lost = summary["packets_lost"] + ear.stats.get("missed", 0)
    out = {
        "source": session.name, "speed": speed, "seconds": duration, "faults": faults,
        "frames_in": summary["frames_in"], "frames_out": summary["frames_out"], "poses_decoded": len(decoded),
        "packets_corrupt": int(corrupt), "packets_lost": int(lost),
        "tracker_lost_events": summary["tracker_lost_events"], "deadline_misses": summary["deadline_misses"],
        "latency_ms": {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())},
        "latency_note": "wall time from the start of the tick that produced a pose to its decoding by the host "
                        "reader (processing, serial transfer, decoding); the look-ahead is reported apart",
        "lookahead_ms": 1000.0 * service.pipeline.lookahead / hz, "ssi_switches": len(service.pipeline.switches),
        "samples": service.pipeline.samples, "frame_ms": summary["frame_ms"], "reopens": summary["reopens"],
        "output_errors": summary["output_errors"],
        "resume_after_replug_s": resume_s,
        "transports": {"opened": sorted(set(opened))}, "errors": errors,
        "latency_ms_samples": [round(x, 3) for x in latency[:20000]],
    }
    if session.gt_pos is not None and len(decoded) > 4:
        idx = np.array([int(round(f.t * hz)) - 1 for f in decoded])
        keep = (idx >= hz) & (idx < len(session.gt_pos))               # skip the first second, like eval
        pred = decoded_positions([f for f, k in zip(decoded, keep) if k])
        gt = session.gt_pos[idx[keep]]
        out["mpjpe_cm"] = float(np.linalg.norm(pred - gt, axis=-1).mean() * 100)
        jerk = np.diff(pred, n=3, axis=0) * hz ** 3
        out["jitter_m_s3"] = float(np.linalg.norm(jerk, axis=-1).mean())
        out["missing_output_frames"] = int(len(np.setdiff1d(np.arange(idx.min(), idx.max() + 1), idx)))
    return out


def load_source(source, transports, faults, seed=0):
    """A recording (.npz session), or a BVH clip / sample take synthesised through the device models."""
    path = str(source)
    if path.endswith(".npz"):
        d = np.load(path, allow_pickle=False)
        if "kind" in d.files:
            return Session.load(path)
    from edge.takes import load_take
    return synthesize(load_take(path), transports, faults, seed)


def main(args):
    try:
        faults = fault_profile(args.faults)
    except ValueError as e:
        print(f"edge replay: {e}", file=sys.stderr)
        return 2
    transports = tuple(args.transport.split(","))
    bad = set(transports) - {"serial", "i2c", "can"}
    if bad:
        print(f"edge replay: unknown transport {sorted(bad)[0]!r}; use serial, i2c, can", file=sys.stderr)
        return 2
    session = load_source(args.source, transports, faults)
    samples = 16 if args.samples == "auto" else int(args.samples)
    result = replay(session, args.speed, samples, args.lookahead, args.seconds, faults, args.bvh, sys.stderr,
                    args.models)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("frames_in", "frames_out", "poses_decoded", "packets_corrupt", "packets_lost", "tracker_lost_events",
            "deadline_misses", "ssi_switches", "mpjpe_cm", "jitter_m_s3")
    print("\n" + "  ".join(f"{k}={result[k]:.4g}" if isinstance(result.get(k), float) else f"{k}={result.get(k)}"
                           for k in keys), file=sys.stderr)
    print(f"latency p50 {result['latency_ms']['p50']:.2f} ms p99 {result['latency_ms']['p99']:.2f} ms "
          f"(+ look-ahead {result['lookahead_ms']:.0f} ms); wrote {args.json}" + (f" and {args.bvh}" if args.bvh else ""),
          file=sys.stderr)
    return 0
