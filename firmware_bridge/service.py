"""`edge run`: the service a board runs. Sources in, poses out, a live status line.

    sources (serial / I2C / CAN) -> FrameSynchronizer -> calibration -> edge Pipeline
        -> POSE_FRAME over serial, VMC, VRChat OSC, BVH recording

The loop never dies on one bad packet: transports count and drop corrupt frames, a source that
fails is reopened with backoff, and every stage's failure is counted in `stats`.
"""
import sys
import time
from collections import deque

import numpy as np

from edge import quat
from edge.calibration import Calibration
from edge.pipeline import Pipeline
from edge.signals import Signals
from firmware_bridge import protocol
from firmware_bridge.config import id_map
from firmware_bridge.samples import HeadsetSample
from firmware_bridge.sync import FrameSynchronizer
from firmware_bridge.transports import TransportError, open_source, parse_url

REOPEN_AFTER_S = 0.25        # how often a failed device is retried


def open_configured(url):
    """open_source with the tracker-name map a serial hub URL carries (?trackers=0:waist,...)."""
    scheme, _, _, query = parse_url(url)
    if scheme == "serial" and "trackers" in query:
        return open_source(url, tracker_names=id_map(query["trackers"]))
    return open_source(url)


class Link:
    """A source plus its reopen policy: a device that fails (unplugged) is retried, not fatal."""

    def __init__(self, url, opener=open_configured):
        self.url, self.opener = url, opener
        self.source = opener(url)          # at start-up a missing device is an error the user must see
        self.down_since = None
        self.reopens = 0

    def drain(self, clock):
        """Everything that has arrived, without waiting."""
        out = []
        if self.source is None:
            if clock() - self.down_since >= REOPEN_AFTER_S:
                try:
                    self.source = self.opener(self.url)
                    self.reopens += 1
                    self.down_since = None
                except TransportError:
                    self.down_since = clock()
            return out
        try:
            while (s := self.source.recv(timeout=0)) is not None:
                out.append(s)
        except (TransportError, OSError):          # unplugged (EIO) or failed for good: retry later
            self.close()
            self.down_since = clock()
        return out

    def close(self):
        if self.source is not None:
            try:
                self.source.close()
            except OSError:
                pass
            self.source = None


class Service:
    def __init__(self, cfg, clock=time.monotonic, status=sys.stderr, opener=open_configured):
        self.cfg, self.clock, self.status = cfg, clock, status
        self.calibration = Calibration.load(cfg.calibration) if cfg.calibration else Calibration()
        self.pipeline = Pipeline(cfg.models or None, samples=cfg.samples, lookahead=cfg.lookahead, fps=cfg.hz)
        self.sync = FrameSynchronizer(trackers=tuple(cfg.tracker_names) or ("waist",), lost_after=cfg.lost_after)
        self.health_order = ["head", "l_hand", "r_hand", *self.sync.trackers]
        self.links = [Link(cfg.headset, opener)] + [Link(u, opener) for u in cfg.trackers]
        self.headset = self.links[0]
        self.pose_out = None
        if cfg.pose_stream.startswith("serial://"):
            self.pose_out = Link(cfg.pose_stream, opener)
        self.outputs = self._open_outputs()
        self.stats = {"ticks": 0, "frames_in": 0, "frames_out": 0, "deadline_misses": 0, "no_input": 0,
                      "samples_in": 0, "output_errors": 0, "tracker_lost_events": 0}
        self.frame_ms = deque(maxlen=600)
        self.latency_ms = deque(maxlen=600)
        self._was_lost = {}
        self._tick_times = np.zeros(256)                    # input tick time by pipeline frame index
        self.health_changes = deque(maxlen=10_000)          # (tick time, source, lost?) when it changes
        self._pose = protocol.PoseFrame(0.0, np.zeros(3), np.tile([1.0, 0, 0, 0], (21, 1)), np.zeros(2))

    def _open_outputs(self):
        outs = []
        cfg = self.cfg
        if cfg.vmc:
            from firmware_bridge.outputs.vmc import VmcSender
            host, _, port = cfg.vmc.rpartition(":")
            outs.append(VmcSender(host, int(port)))
        if cfg.vrchat:
            from firmware_bridge.outputs.vrchat import VrchatSender
            host, _, port = cfg.vrchat.rpartition(":")
            outs.append(VrchatSender(host, int(port)))
        if cfg.bvh:
            from pathlib import Path
            from firmware_bridge.outputs.bvh_writer import BvhWriter
            Path(cfg.bvh).parent.mkdir(parents=True, exist_ok=True)
            outs.append(BvhWriter(cfg.bvh, fps=cfg.hz))
        return outs

    # ------------------------------------------------------------------ loop
    def run(self, seconds=None, stop=None):
        """Run at the model rate on this service's clock until `seconds` pass or `stop()` says so."""
        period = 1.0 / self.cfg.hz
        start = self.clock()
        next_tick = start + period
        last_status = start
        try:
            while (seconds is None or self.clock() - start < seconds) and not (stop and stop()):
                self.poll()
                now = self.clock()
                if now >= next_tick:
                    self.tick(now)
                    next_tick += period
                    if next_tick < self.clock():          # fell behind: skip, do not burst
                        next_tick = self.clock() + period
                    if now - last_status >= 0.5:
                        self.show_status()
                        last_status = now
                else:
                    time.sleep(min(0.001, next_tick - now))
        finally:
            self.close()
            self.show_status(final=True)
        return self.summary()

    def step(self, now):
        """One model tick driven from outside (the simulator): read what arrived, then tick."""
        self.poll()
        self.tick(now)

    def poll(self):
        for link in self.links:
            for s in link.drain(self.clock):
                self.stats["samples_in"] += 1
                s.received = self.clock()          # one clock for the synchroniser, whatever the transport
                if isinstance(s, HeadsetSample):
                    self.sync.add_headset(s)
                else:
                    self.sync.add_tracker(s)

    def tick(self, now):
        """Sync, pipeline and outputs for the model tick at `now`. Processing time is wall time
        (perf_counter), so deadline misses are real even when `now` is simulated."""
        self.stats["ticks"] += 1
        t0 = time.perf_counter()
        sig, health = self.sync.frame(now)
        if sig is None:
            self.stats["no_input"] += 1
            return
        self.stats["frames_in"] += 1
        self._tick_times[self.pipeline.t + 1 & 255] = now
        for name, lost in health.lost.items():
            if lost != self._was_lost.get(name, False):
                self.health_changes.append((now, name, lost))
                if lost:
                    self.stats["tracker_lost_events"] += 1
            self._was_lost[name] = lost
        pose = self.pipeline.step(self._calibrated(sig))
        if pose is not None:
            self._emit(pose, health)
        elapsed = time.perf_counter() - t0
        self.frame_ms.append(elapsed * 1000)
        if elapsed > 1.0 / self.cfg.hz:
            self.stats["deadline_misses"] += 1
        newest = self.sync.streams["head"].newest
        if np.isfinite(newest):
            self.latency_ms.append((self.clock() - newest) * 1000)

    def _calibrated(self, sig):
        """Apply mounting offsets and scale the user onto the canonical body (around the floor origin)."""
        cal = self.calibration
        s = cal.height_scale
        return Signals(sig.head_pos * s, sig.head_rot, sig.hand_pos * s, sig.hand_rot,
                       cal.body_rotation("waist", sig.waist_rot), sig.waist_acc)

    def _emit(self, pose, health):
        self.stats["frames_out"] += 1
        p = self._pose
        p.t = self._tick_times[pose.frame & 255]          # the time the pose is of (its input tick)
        p.root_pos = pose.positions[0] / self.calibration.height_scale
        p.rotations = quat.from_matrix(pose.rotations)
        p.contacts = pose.contacts
        p.num_samples = self.pipeline.samples
        p.ssi_flags = protocol.SSI_IN_TRANSITION if pose.transition else 0
        p.trackers_lost = sum(1 << i for i, name in enumerate(self.health_order) if health.lost.get(name, False))
        target = self.headset if self.cfg.pose_stream == "headset" else self.pose_out
        try:
            if target is not None and target.source is not None:
                target.source.send_pose(p)
        except (TransportError, ValueError, AttributeError):
            self.stats["output_errors"] += 1
        for out in self.outputs:
            try:
                (out.write_frame if hasattr(out, "write_frame") else out.send)(pose)
            except (OSError, ValueError):
                self.stats["output_errors"] += 1

    # ------------------------------------------------------------------ reporting
    def health_timeline(self):
        """Lost / recovered events per source: {"events": [{"t": .., "source": .., "lost": ..}, ...]}."""
        return {"events": [{"t": round(t, 4), "source": n, "lost": bool(l)} for t, n, l in self.health_changes]}

    def summary(self):
        fm = np.array(self.frame_ms) if self.frame_ms else np.zeros(1)
        lat = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        live = [l.source for l in self.links if l.source is not None]
        corrupt = sum(s.stats.get("corrupt", 0) for s in live)
        lost = sum(s.stats.get("missed", 0) + s.stats.get("lost", 0) for s in live)
        return {**self.stats, "packets_corrupt": corrupt, "packets_lost": lost, "ssi_switches": len(self.pipeline.switches),
                "samples": self.pipeline.samples, "lookahead_frames": self.pipeline.lookahead,
                "frame_ms": {"p50": float(np.median(fm)), "p99": float(np.percentile(fm, 99))},
                "input_age_ms": {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99))},
                "reopens": sum(l.reopens for l in self.links)}

    def show_status(self, final=False):
        if self.status is None:
            return
        s = self.summary()
        lost = [n for n, v in self._was_lost.items() if v]
        line = (f"edge run | in {s['frames_in']} out {s['frames_out']} | N={s['samples']} switches {s['ssi_switches']} "
                f"| frame p99 {s['frame_ms']['p99']:.1f} ms | late {s['deadline_misses']} | corrupt {s['packets_corrupt']} "
                f"| lost: {','.join(lost) or '-'}")
        tty = hasattr(self.status, "isatty") and self.status.isatty()
        self.status.write(("\r" + line + "\x1b[K" + ("\n" if final else "")) if tty else (line + "\n" if final else ""))
        self.status.flush()

    def close(self):
        for link in self.links + ([self.pose_out] if self.pose_out else []):
            link.close()
        for out in self.outputs:
            out.close()
