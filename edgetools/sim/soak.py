"""`edge soak`: one board service for hours, on every transport at once, with faults mixed in (issue #55).

The board under test is `edge run`'s Service, as `edge replay` drives it, in real time: the headset and
the tracker hub on ptys, the waist BNO055 on the I2C fake, the feet on CAN, the shins over SlimeVR UDP.
What they send is made a part at a time (`--part-s`, a minute) from recordings in turn, in a process
of its own a few parts ahead, each part on from the last: the same device clocks, frame counters and
SlimeVR packet numbers running on, so the board sees one long session. Each part carries one fault of
SCHEDULE (corrupt bytes, a SlimeVR tracker silent, the headset unplugged, a host stall, a burst of
foreign SlimeVR datagrams, a CAN bus-off, or none) `FAULT_AT` of the way in.

Every `--sample-s` (at a part's end, between faults) it samples RSS, descriptors, threads, the frames in
and out per source, the frame's p50/p99 and late ticks, the lag, and the heading observer's correction,
as JSON lines; the summary (`--json`) says whether anything grew or stopped, and `ok`.

A tick is late when it ends after the next tick's release. Whose doing it was:
- own: the tick's thread used more CPU than a period (the board's own work did not fit);
- fault: during an injected fault or the second after it (a stall, a reopen);
- harness: the harness began the tick more than half a period late (the simulator fell behind, not
  the board; the soak's measurement is then not a measurement of the board);
- host: the rest (the thread was runnable and not run: the host, a VM's steal time).
"""
import json
import os
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from edgetools.cpulimit import busy_seconds
from edgetools.sim import scheme
from edgetools.sim.bno055_fake import ChipBehaviour, FakeBNO055
from edgetools.sim.replay import ReplayBench
from edgetools.sim.replay_report import rss_mb
from edgetools.sim.stream_metrics import StreamMetrics, score

TRANSPORTS = ("serial", "i2c", "can", "slimevr")
# Every transport at once: the waist on I2C, the feet on CAN, the thighs on the serial hub, the shins on SlimeVR.
PLACE = {"i2c": ["waist"], "hub": ["l_thigh", "r_thigh"], "can": ["l_foot", "r_foot"], "slimevr": ["l_shin", "r_shin"]}
TRACKERS = ("l_foot", "r_foot", "l_thigh", "r_thigh", "l_shin", "r_shin")
FAULT_AT = 0.4              # of the way into a part
RECOVER_S = 5.0             # every source in use and poses reaching the host this long after a fault ends
LATE_KINDS = ("own", "fault", "host", "harness")


@dataclass(frozen=True)
class Fault:
    """One fault of the schedule: `seconds` long from FAULT_AT into its part. `synth` shapes the traffic
    when the part is made (bit errors, a bus-off); `live` is done to the devices as it plays. `moves`:
    the summary counter that must move for the fault to count as seen."""
    name: str
    seconds: float
    moves: str
    synth: dict = field(default_factory=dict)
    live: str = ""


SCHEDULE = (
    Fault("corrupt bytes", 0.0, "packets_corrupt", synth={"ber": 2e-4}),
    Fault("SlimeVR tracker silent 3 s", 3.0, "tracker_lost_events", live="silence"),
    Fault("headset unplugged 1 s", 1.0, "reopens", live="unplug"),
    Fault("50 ms host stall", 0.05, "deadline_misses", live="stall"),
    Fault("foreign SlimeVR burst 2 s", 2.0, "packets_foreign", live="flood"),
    Fault("CAN bus-off 1 s", 1.0, "tracker_lost_events", synth={"busoff_s": 1.0}),
    Fault("none", 0.0, ""),
)


# ----------------------------------------------------------------------------- the parts

@lru_cache(maxsize=8)
def _take(path):
    from motion.takes import load_take
    return load_take(path)


def take_window(take, start_s, seconds):
    """`seconds` of `take` from `start_s` on, wrapping round its end (the body jumps at the seam)."""
    from dataclasses import fields

    from edge.signals import Signals
    n, fps = take.frames, take.fps
    idx = (int(round(start_s * fps)) + np.arange(int(np.ceil(seconds * fps)) + 2)) % n
    sig = take.signals
    return type(take)(take.name, Signals(**{f.name: getattr(sig, f.name)[idx] for f in fields(sig)}),
                      take.gt_pos[idx], fps, {k: v[idx] for k, v in (take.imu or {}).items()})


class PackedFrames:
    """Frame i of one byte string, cut at `ends`."""

    def __init__(self, blob, ends):
        self.blob, self.ends = blob, ends

    def __getitem__(self, i):
        return self.blob[(self.ends[i - 1] if i else 0):self.ends[i]]

    def __len__(self):
        return len(self.ends)


class PackedLog:
    """A SerialLog as its times, frame ends and one byte string: a part crosses from the process that
    made it in a few memory copies. Unpickled as lists of small bytes it held the GIL for ~15 ms, a
    late tick of the board's that was the harness's doing. No reference cycles: a part must be freed
    when the devices let go of it, not at the next full garbage collection (a log that was its own
    `frames` kept a part a minute alive for good: 1.5 MB a minute of the soak's own)."""

    def __init__(self, log):
        self.t = np.asarray(log.t, np.float64)
        self.frames = PackedFrames(b"".join(log.frames), np.cumsum([len(f) for f in log.frames], dtype=np.int64))


def make_part(index, clips, part_s, clocks=None):
    """Part `index` of a soak: its clip (in turn), where in the clip, its fault, its traffic (a Session
    whose times run from index * part_s, its logs packed, no ground truth)."""
    from edgetools.sim.session import synthesize
    fault = SCHEDULE[index % len(SCHEDULE)]
    clip = clips[index % len(clips)]
    take = _take(clip)
    window = take_window(take, (index // len(clips)) * part_s, part_s)
    synth = dict(fault.synth)
    if "busoff_s" in synth:
        synth["busoff_at"] = FAULT_AT * part_s
    part = synthesize(window, TRANSPORTS, synth, seed=index, seconds=part_s, trackers=TRACKERS, place=PLACE,
                      start=index * part_s, clocks=clocks)
    part.headset, part.hub = PackedLog(part.headset), PackedLog(part.hub)
    part.slimevr = {mac: PackedLog(log) for mac, log in part.slimevr.items()}
    part.gt_pos = None
    return part


def _worker_start(board_cores):
    """Below the board, and on another core when the soak was given some (taskset): a busy part maker
    must not be the board's late frame."""
    os.nice(10)
    others = set(range(os.cpu_count() or 1)) - set(board_cores)
    if others:
        try:
            os.sched_setaffinity(0, others)
        except OSError:
            pass


class Parts:
    """Parts made `ahead` in a process of its own (forkserver: nothing of the board's threads), in order."""

    def __init__(self, clips, part_s, count, ahead=3):
        import multiprocessing as mp
        self.clips, self.part_s, self.count = tuple(map(str, clips)), part_s, count
        self.pool = ProcessPoolExecutor(1, mp_context=mp.get_context("forkserver"), initializer=_worker_start,
                                        initargs=(sorted(os.sched_getaffinity(0)),))
        first = self.pool.submit(make_part, 0, self.clips, part_s).result()
        self.clocks = first.meta["clocks"]
        self.ready = [first]
        self.pending = [self.pool.submit(make_part, i, self.clips, part_s, self.clocks)
                        for i in range(1, min(ahead + 1, count))]
        self.next_index = 1 + len(self.pending)

    def take(self):
        """The next part (waits for it if it is not made yet); keeps `ahead` in the making."""
        if self.ready:
            return self.ready.pop(0)
        if not self.pending:
            return None
        part = self.pending.pop(0).result()
        if self.next_index < self.count:
            self.pending.append(self.pool.submit(make_part, self.next_index, self.clips, self.part_s, self.clocks))
            self.next_index += 1
        return part

    def close(self):
        for f in self.pending:
            f.cancel()
        self.pool.shutdown(wait=True, cancel_futures=True)


class WaistFeed:
    """The BNO055 fake's motion, a part at a time: the recorded output registers at time t."""

    def __init__(self):
        self.parts = []          # (start, quaternions, accelerations), at 100 Hz

    def add(self, session):
        q, valid = session.i2c_quat, np.all(np.isfinite(session.i2c_quat), axis=1)
        q = np.where(valid[:, None], q, [1.0, 0, 0, 0])
        self.parts.append((float(session.i2c_t[0]) if len(session.i2c_t) else 0.0, q, session.i2c_accel))
        del self.parts[:-2]     # the one playing and the next

    def __call__(self, t):
        start, q, a = self.parts[-1] if t >= self.parts[-1][0] or len(self.parts) == 1 else self.parts[0]
        i = min(max(int((t - start) * 100.0), 0), len(q) - 1)
        return q[i], a[i]


# ----------------------------------------------------------------------------- the bench

class SoakBench(ReplayBench):
    """ReplayBench with its devices fed a part at a time, the schedule's faults done live, and each tick
    timed and judged (late, and whose doing)."""

    def __init__(self, parts, minutes, sample_s):
        self.parts, self.part_s = parts, parts.part_s
        first = parts.take()
        super().__init__(first, "realtime", {})
        self.waist = WaistFeed()
        self.waist.add(first)
        chip = FakeBNO055(self.waist, clock=self.clock, sleep=self.clock.sleep,
                          behaviour=ChipBehaviour(boot_seconds=0.0, calibration_seconds=(0, 0, 0), seed=1))
        scheme.BENCH[f"{self.name}-waist"] = scheme.BenchDevice(chip, self.clock, self.clock.sleep)
        self.playing, self.upcoming = first, parts.take()
        self.index = 0
        self.end_s = minutes * 60
        self.sample_s = sample_s
        self.flood_stop = None
        self.live = None            # (fault, start, end) of the live fault playing
        self.events = []            # one dict per injected fault

    def _slimevr_opened(self, source):
        self.slimevr_address = source.address         # where a foreign device's burst goes
        super()._slimevr_opened(source)

    # --- the parts, fed to the devices as the clock reaches them
    def devices_emit(self, now):
        while self.upcoming is not None and now >= self.upcoming.meta["start"]:
            super()._devices_emit(self.upcoming.meta["start"] - 1e-9)      # what the last part had left
            self._feed(self.upcoming)
        self._live_faults(now)
        super()._devices_emit(now)

    def _feed(self, part):
        for name in ("headset", "hub"):
            if name in self.devices:
                self.devices[name].log, self.devices[name].next = getattr(part, name), 0
        if self.can_dev is not None:
            self.can_dev.s, self.can_dev.next = part, 0
        for dev in self.slimevr_devices:
            dev.log, dev.next = part.slimevr[dev.mac], 0
        self.waist.add(part)
        self.playing, self.index = part, self.index + 1
        self.upcoming = self.parts.take()

    # --- the schedule
    def fault_of(self, index):
        return SCHEDULE[index % len(SCHEDULE)]

    def _live_faults(self, now):
        """Start the playing part's fault at FAULT_AT, end a live one when its time is up."""
        fault, start = self.fault_of(self.index), self.index * self.part_s + FAULT_AT * self.part_s
        judged = start + fault.seconds + RECOVER_S <= self.end_s        # a fault the soak can see the end of
        if fault.name != "none" and judged and now >= start and (not self.events or self.events[-1]["part"] != self.index):
            self.events.append({"part": self.index, "fault": fault.name, "at_s": round(start, 3),
                                "ends_s": round(start + fault.seconds, 3), "counter": fault.moves,
                                "before": self.counter(fault.moves), "counted": False, "recovered_s": None})
            self.live = (fault, start, start + fault.seconds)
            self._begin(fault, now)
        if self.live is not None and now >= self.live[2]:
            self._end(self.live[0], now)
            self.live = None

    def _begin(self, fault, now):
        if fault.live == "silence":
            self.slimevr_devices[-1].unplug(now, fault.seconds)
        elif fault.live == "unplug":
            self._plugged.clear()
            time.sleep(0.005)                   # let the host reader leave the fd before it closes
            self.devices["headset"].unplug()
        elif fault.live == "stall":
            time.sleep(fault.seconds)           # the harness and the board's tick thread both stop
        elif fault.live == "flood":
            import multiprocessing as mp
            from edgetools.sim.devices import flood
            ctx = mp.get_context("forkserver")
            self.flood_stop = ctx.Event()
            address = self.slimevr_address
            self.flooder = ctx.Process(target=flood, args=(address, 2000, self.flood_stop), daemon=True)
            self.flooder.start()

    def _end(self, fault, now):
        if fault.live == "unplug":
            self.devices["headset"].plug()
            self.ear.fd = self.devices["headset"].master
            self._plugged.set()
        elif fault.live == "flood":
            self.flood_stop.set()
            self.flooder.join(2.0)
            self.flooder.close()
            self.flood_stop = self.flooder = None

    def counter(self, name):
        if not name:
            return 0
        s = self.service.summary()
        if name == "packets_foreign":           # what the SlimeVR source dropped: corrupt, unknown, strangers
            return s["packets_corrupt"] + s["packets_unknown"] + s.get("samples_unknown_tracker", 0)
        return s[name]

    def judge_faults(self, now, last_pose_t):
        """Each fault: counted (its counter moved), recovered (every source in use and poses at the host
        within RECOVER_S of its end)."""
        lost = bool(self.service.sources_lost())
        for e in self.events:
            if not e["counted"] and self.counter(e["counter"]) > e["before"]:
                e["counted"] = True
            if e["recovered_s"] is None and now >= e["ends_s"] and not lost and last_pose_t >= e["ends_s"]:
                e["recovered_s"] = round(max(now - e["ends_s"], 0.0), 3)

    def close(self):
        if self.flood_stop is not None:
            self.flood_stop.set()
        super().close()


# ----------------------------------------------------------------------------- the run

class Soak:
    """The tick loop, its per-tick arrays (made once: a soak measures the board's memory, not its
    own), the samples and the verdict."""

    def __init__(self, bench, minutes, sample_s, lines, status):
        self.bench, self.minutes, self.sample_s, self.lines, self.status = bench, minutes, sample_s, lines, status
        self.samples = []
        self._cpu_mark = self._cpu_now()

    @staticmethod
    def _cpu_now():
        """(the machine's busy CPU seconds, this process's, the monotonic clock) for the load each sample reports."""
        t = os.times()
        return busy_seconds(), t.user + t.system, time.monotonic()

    def _load(self):
        """Cores busy since the last sample: the machine's and this process's (the board and the simulated
        devices). The rest is the parts' worker and everything else on the machine: on a VM another
        process's memory traffic is charged to the tick's CPU (edgetools.profile, CoreNeighbours), so a
        late tick of the board's own is read beside it."""
        (busy0, own0, t0), now = self._cpu_mark, self._cpu_now()
        self._cpu_mark = now
        wall = max(now[2] - t0, 1e-9)
        return {"machine_cores": None if busy0 is None or now[0] is None else round((now[0] - busy0) / wall, 3),
                "soak_process_cores": round((now[1] - own0) / wall, 3)}

    def run(self):
        b = self.bench
        service = b.service
        hz = service.cfg.hz
        period = 1.0 / hz
        ticks = int(round(self.minutes * 60 * hz))
        self.hz, self.frame_ms = hz, np.full(ticks + 1, np.nan)
        self.cpu_ms = np.full(ticks + 1, np.nan)
        self.late = np.full(ticks + 1, 0, np.int8)          # 0 on time, else 1 + LATE_KINDS index (np.full:
        # every page touched now, not a few KB a minute as the ticks reach them, which reads as growth)
        b.metrics = StreamMetrics(ticks, hz, None, service.pipeline.lookahead)
        b._ticks_by_us = {}
        b.clock.t0 = time.monotonic()
        next_sample, next_status, last_pose_t, k = self.sample_s, 0.0, 0.0, 0
        self.started = time.time()
        try:
            for k in range(1, ticks + 1):
                now = k / hz
                behind = b.clock() - now            # > 0: the harness comes to this tick late
                b._wait_until(now)
                b.devices_emit(now)
                self._tick(k, now, period, behind)
                if b.metrics.decoded and np.isfinite(b.metrics.t[max(k - 30, 0):k + 1]).any():
                    last_pose_t = now
                if k % 15 == 0:                     # four times a second: a summary is not free
                    b.judge_faults(now, last_pose_t)
                if now >= next_status:
                    self._show(now, k)
                    next_status = now + 5.0
                if now >= next_sample - 1e-9:
                    self._sample(now, k)
                    next_sample += self.sample_s
        except KeyboardInterrupt:                   # Ctrl-C: say what was measured
            pass
        self.ticks_run = k
        return self.ticks_run

    def _tick(self, k, now, period, behind):
        b, service = self.bench, self.bench.service
        step_now, index, wall = b.clock(), service.pipeline.t + 1, time.perf_counter()
        b._ticks_by_us[int(round(step_now * 1e6))] = (index, wall)
        b.metrics.wall[index] = wall
        b.metrics.wall.pop(index - 300, None)
        if len(b._ticks_by_us) > 600:
            b._ticks_by_us.pop(next(iter(b._ticks_by_us)))
        cpu0 = time.thread_time()
        try:
            service.step(step_now, due=now + period)
        except Exception as e:                   # the soak goes on; the verdict says what broke
            b.errors.append(f"tick {k}: {type(e).__name__}: {e}")
        cpu, took = time.thread_time() - cpu0, time.perf_counter() - wall
        self.frame_ms[k], self.cpu_ms[k] = took * 1000, cpu * 1000
        if b.clock() > now + period:
            live = b.live is not None or any(e["at_s"] <= now <= e["ends_s"] + 1.0 for e in b.events[-1:])
            kind = "fault" if live else "own" if cpu > period else "harness" if behind > period / 2 else "host"
            self.late[k] = 1 + LATE_KINDS.index(kind)
        score(b.inbox, b.metrics, b._ticks_by_us, b.replug)

    def _window(self, k):
        lo = self.samples[-1]["tick"] + 1 if self.samples else 1
        return slice(lo, k + 1)

    def _sample(self, now, k):
        b, s = self.bench, self.bench.service.summary()
        w = self._window(k)
        frame = self.frame_ms[w]
        frame = frame[np.isfinite(frame)]
        late = {kind: int((self.late[w] == 1 + i).sum()) for i, kind in enumerate(LATE_KINDS)}
        heading = b.service.pipeline.heading
        row = {"t_min": round(now / 60, 4), "tick": k, "rss_mb": round(rss_mb(), 2), "fds": len(os.listdir("/proc/self/fd")),
               "threads": threading.active_count(), "frames_in": s["frames_in"], "frames_out": s["frames_out"],
               "host_poses": int(b.metrics.decoded), "packets_corrupt": s["packets_corrupt"],
               "packets_lost": s["packets_lost"], "reopens": s["reopens"],
               "sources": {url.split("?")[0]: link["counts"].get("frames", 0) for url, link in s["links"].items()},
               "frame_ms_p50": round(float(np.percentile(frame, 50)), 3) if len(frame) else None,
               "frame_ms_p99": round(float(np.percentile(frame, 99)), 3) if len(frame) else None,
               "late": late, "lag_ms_p99": s.get("motion_to_pose_lag_ms_last_10s", {}).get("p99"),
               "heading_correction_deg": (round(float(np.degrees(np.abs(heading.offset).max())), 3)
                                          if heading is not None else None),
               "samples": s["samples"], "faults": len(b.events), "recovered": sum(e["recovered_s"] is not None for e in b.events),
               "load": self._load()}
        self.samples.append(row)
        if self.lines is not None:
            self.lines.write(json.dumps(row) + "\n")
            self.lines.flush()

    def _show(self, now, k):
        if self.status is None:
            return
        late = {kind: int((self.late[:k + 1] == 1 + i).sum()) for i, kind in enumerate(LATE_KINDS)}
        frame = self.frame_ms[max(1, k - 600):k + 1]
        e = self.bench.events
        print(f"edge soak | {now / 60:.1f}/{self.minutes:g} min | rss {rss_mb():.1f} MB | fds {len(os.listdir('/proc/self/fd'))} "
              f"| threads {threading.active_count()} | out {self.bench.service.stats['frames_out']} | frame p99 "
              f"{np.nanpercentile(frame, 99):.1f} ms | late own {late['own']} fault {late['fault']} host {late['host']} "
              f"harness {late['harness']} | faults {sum(x['recovered_s'] is not None for x in e)}/{len(e)}",
              file=self.status, flush=True)

    # --- the verdict
    def verdict(self):
        """The summary: growth after warm-up, late ticks by whose doing, every fault, and the checks."""
        b, k = self.bench, self.ticks_run
        rows = self.samples
        minutes = k / self.hz / 60
        warm = rows[max(1, len(rows) // 10):] if len(rows) > 2 else rows[-1:]
        t = np.array([r["t_min"] for r in warm]) / 60
        rss = np.array([r["rss_mb"] for r in warm])
        slope = float(np.polyfit(t, rss, 1)[0]) if len(warm) > 2 and np.ptp(t) > 0 else 0.0
        span_h = float(np.ptp(t)) if len(warm) else 0.0
        late = {kind: int((self.late[:k + 1] == 1 + i).sum()) for i, kind in enumerate(LATE_KINDS)}
        p99 = self.p99_by_10_minutes(k)
        events = b.events
        out = {"minutes": round(minutes, 3), "ticks": k, "hz": self.hz,
               "rss_growth_mb_per_h": round(slope, 3), "rss_mb": {"start": rows[0]["rss_mb"] if rows else None,
                                                                  "after_warmup": warm[0]["rss_mb"] if warm else None,
                                                                  "end": rows[-1]["rss_mb"] if rows else None},
               "fd_growth": (warm[-1]["fds"] - warm[0]["fds"]) if warm else 0,
               "thread_growth": (warm[-1]["threads"] - warm[0]["threads"]) if warm else 0,
               "own_late_frames": late["own"], "late_frames": late,
               "faults_injected": len(events), "faults_counted": sum(e["counted"] for e in events),
               "faults_recovered": sum(e["recovered_s"] is not None for e in events),
               "frames_out": b.service.stats["frames_out"], "host_poses": int(b.metrics.decoded),
               "frame_ms": {"p50": float(np.nanpercentile(self.frame_ms[1:k + 1], 50)),
                            "p99": float(np.nanpercentile(self.frame_ms[1:k + 1], 99))} if k else {},
               "frame_ms_p99_by_10_minutes": p99, "errors": b.errors[:20], "faults": events, "samples": len(rows),
               # where the board's own late ticks fell, beside what the machine was doing then
               "own_late_at": [{"t_min": r["t_min"], "own": r["late"]["own"], "load": r.get("load")}
                               for r in rows if r["late"].get("own")]}
        # growth judged over the span after warm-up: 1 MB an hour. A run of minutes cannot tell that from the
        # allocator's warm-up (a minute grows 1-3 MB, then it is flat: docs/benchmarks.md, "Soaks"), so it
        # is allowed 5 MB: it catches a leak of megabytes a minute, the hours catch the rest.
        checks = {"ran_the_whole_time": k >= round(self.minutes * 60 * self.hz),
                  "rss_flat": slope * span_h <= max(1.0 * span_h, 5.0),
                  "fds_flat": out["fd_growth"] <= 0, "threads_flat": out["thread_growth"] <= 0,
                  "no_own_late_frames": late["own"] == 0,
                  "every_fault_counted": all(e["counted"] for e in events),
                  "every_fault_recovered": all(e["recovered_s"] is not None for e in events),
                  "counters_moving": all(b2["frames_out"] > a2["frames_out"] and b2["host_poses"] > a2["host_poses"]
                                         and all(b2["sources"].get(s, 0) > n for s, n in a2["sources"].items())
                                         for a2, b2 in zip(rows, rows[1:], strict=False)),
                  "no_tick_errors": not b.errors,
                  "harness_kept_up": late["harness"] <= 0.01 * k}
        if len(p99) > 1:        # the tail steady: every later ten minutes' p99 within 20 % of the first's
            checks["p99_steady"] = all(x <= 1.2 * p99[0] for x in p99[1:])
        out["checks"] = checks
        out["ok"] = all(checks.values())
        return out

    def p99_by_10_minutes(self, k):
        per = int(600 * self.hz)
        return [round(float(np.nanpercentile(self.frame_ms[a:a + per], 99)), 3)
                for a in range(1, k + 1 - per + 1, per)]


def _say(summary):
    c = summary["checks"]
    failed = [name for name, good in c.items() if not good]
    lf = summary["late_frames"]
    return (f"edge soak: {summary['minutes']:g} min, {summary['frames_out']} poses out, RSS "
            f"{summary['rss_growth_mb_per_h']:+.2f} MB/h after warm-up, fds {summary['fd_growth']:+d}, threads "
            f"{summary['thread_growth']:+d}, late frames of its own {lf['own']} (in faults {lf['fault']}, the host's "
            f"{lf['host']}, the harness's {lf['harness']}), faults recovered {summary['faults_recovered']}/"
            f"{summary['faults_injected']}: " + ("ok" if not failed else "FAILED " + ", ".join(failed)))


def default_clips():
    """The bundled walk, on a machine without ../shared."""
    from pathlib import Path
    return [str(Path(__file__).resolve().parents[2] / "samples" / "cmu_09_12_walk.npz")]


def main(args):
    from pathlib import Path
    clips = args.source or default_clips()
    for c in clips:
        if not Path(c).exists():
            print(f"edge soak: {c}: no such file (a BVH clip or a sample take)", file=sys.stderr)
            return 2
    if args.minutes <= 0 or args.part_s < 5 or args.sample_s < args.part_s or args.sample_s % args.part_s:
        print("edge soak: --minutes > 0, --part-s >= 5 and --sample-s a multiple of --part-s "
              "(samples are taken between parts, with no fault playing)", file=sys.stderr)
        return 2
    count = int(np.ceil(args.minutes * 60 / args.part_s)) + 1
    parts = Parts(clips, args.part_s, count)
    lines_path = Path(args.lines or Path(args.json).with_suffix(".jsonl"))
    lines_path.parent.mkdir(parents=True, exist_ok=True)
    bench = None
    try:
        with open(lines_path, "w") as lines:
            bench = SoakBench(parts, args.minutes, args.sample_s)
            runtime = {"samples": args.samples, "adaptive": args.samples == "auto", "precision": args.precision}
            bench.open_service({k: v for k, v in runtime.items() if k != "samples" or v != "auto"}, None,
                               None, True)
            bench.open_host(None)
            soak = Soak(bench, args.minutes, args.sample_s, lines, sys.stderr)
            soak.run()
            summary = soak.verdict()
    finally:
        if bench is not None:
            bench.close()
        parts.close()
    summary.update(clips=clips, part_s=args.part_s, sample_s=args.sample_s, lines=str(lines_path),
                   schedule=[f.name for f in SCHEDULE], cpu=_cpu_name())
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(summary, indent=2))
    print(_say(summary))
    return 0 if summary["ok"] else 1


def _cpu_name():
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return ""
