"""`edge profile`: how many SSI samples and refinement steps fit a CPU budget, measured on the real pipeline.

    edge profile [--cpu-quota Q] [--hz H] [--samples N|auto] [--refine-steps K] [--frames F] [--precision fp32|int8] --json OUT
    edge profile --samples 128 --adaptive --frames 4200 --hog-at 15 --hog-seconds 30 --hog-procs 5 --json OUT

A worker process runs the board's per-frame path on synthesised input (the bundled sample's tracker
signals, looped): FrameSynchronizer.frame -> Pipeline.step -> POSE_FRAME encoding, with frames released
at H Hz in real time (it sleeps until each frame's release time). Frame k is released at t0 + k/H and
must be done by the next release; one that finishes later is a deadline miss. `frame_ms` is the
response time, release to done (throttling waits and late starts included).

CPU limit. Where the OS allows it (root, a writable cgroup v1 `cpu` hierarchy or cgroup v2 with the cpu
controller), the worker runs in its own child cgroup with a CFS quota of Q x cfs_period and is pinned
to one core, so it gets Q of one core; the group is removed afterwards. A CFS quota is enforced per
period: with Q = 0.25 and the default 100 ms period the worker may run 25 ms and is then frozen for
75 ms, which would make a 60 Hz loop (16.7 ms frames) miss whole runs of frames however cheap each frame
is. We set cfs_period_us to 10 ms (--period-ms): the worker then runs 2.5 ms in every 10 ms, so a frame
that needs c ms of CPU is done after about c/Q ms plus at most (1-Q) x 10 ms of waiting for the next
period. (On a board, set the service's period the same way: systemd CPUQuotaPeriodSec=10ms.)
Elsewhere the worker is only pinned to one core, quota_enforced is false, and the budget below is the
modelled one (CPU time per frame against Q x 1000/H ms).

N and K together. Refinement steps (K, edge.refine) only cost while a headset's target is live; the
profile measures the worst case, a target live every frame (--refine-steps K, default 2: the most
steps, as [refine] steps; 0: no target and N alone). --samples auto probes the governor's rungs
(edge.governor.rungs, cheapest first: (1,0), (1,1), (2,1), ..., (32,1), (32,2), (48,2), ... (128,2))
in turn (--probe-frames real-time frames each, under the same limit; a probe that does not fit is
repeated once; one late frame in a probe is taken for a stall) and chooses the highest rung whose p99
frame time leaves 20 % headroom (--headroom):
p99 <= 0.8 x 1000/H ms (quota enforced; the quota's effect is in the measured time) or p99 CPU time
<= 0.8 x Q x 1000/H ms (not enforced). It then runs --frames frames there, the run whose numbers are
reported; if that run misses deadlines it steps down one rung and runs again, except that a run with
one or two late frames (a stall of the machine is not a verdict on N) is first made once more at the
same rung (every attempt is kept in the JSON, at most six). Deploy with the chosen N as [runtime]
samples and K as [refine] steps.

Contention (--hog-at S [--hog-seconds D] [--hog-procs K]): K busy processes start S seconds into the
measured run, on the worker's core but outside its cgroup, and stop D seconds later. With
--adaptive the deadline watchdog (edge.governor, the same one `edge run` uses) lowers N while
frames run late and raises it again when there is slack (and K with it, along the same rungs); `contention` in the JSON has deadline
misses and N before, during and after the hog, every change of N and each frame's time, and
`edge report OUT --out DIR` draws them. Without --adaptive the same run shows what a fixed N does.
A frame whose deadline passed before it could start is skipped and counted as a miss, as `edge run`
does (it resynchronises instead of bursting).

The host's stalls apart from the frame's cost. Every measured frame records its own CPU time (the
thread's), how long it waited to run (the thread's run_delay in /proc/self/task/TID/schedstat) and the
VM's steal time (/proc/stat) over the run. A late frame whose own CPU time would have made the deadline
at the quota (CPU / Q plus one throttled CFS period, (1 - Q) x period, where the quota is enforced; its
CPU time alone where it is not) was late because the host did not run it: it is counted as a host stall
(`host` in the JSON), beside the frame's own misses, and neither a probe nor a measured run is judged on
it. Skipped frames take the cause of the frame that made them late. N is chosen on the frames' own
cost: the p99 of the frames that were not stalled, and their own misses.

Neighbours on the core. What the thread's CPU clock says is the frame's own only if nothing else
works on its core: where the kernel charges interrupt work to the running task (no IRQ time
accounting, as on the VMs this was built on), another process's memory traffic shows up as the
frame's CPU time (a neighbour allocating and freeing 512 MB in a loop at nice 19 made frames of
22-26 ms out of 1.2, with none of the frame's own page faults). `core_neighbours` in the JSON is the
share of the core other tasks used during the run, and over 2 % it is warned of: profile on a quiet core.

Stage timings, every measured frame, from the live code itself: `sync`, `pipeline_step` and
`output_encoding` are the board service's own tick (Service.tick_marks, wall time), fed through
sim:// sources by its own links; the stages inside Pipeline.step (features, decoder, poses,
criteria, selection, emit) are the live step's own stamps (Pipeline.timing, thread CPU time, so a
throttled period does not count). The loop is paced by the service's Pacer.
"""
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from edge.governor import rungs
from edge.inference import DEFAULT_PRECISION

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"
from edgetools.cpulimit import CGROUP_V1, CGROUP_V2, CpuLimit, Hog, busy_seconds  # noqa: F401  (CGROUP_*: tests read them)


def add_arguments(p):
    p.add_argument("--cpu-quota", type=float, default=None,
                   help="fraction of one core the service may use, e.g. 0.25 (default: a whole core)")
    p.add_argument("--hz", type=float, default=60.0, help="frame rate (default 60)")
    p.add_argument("--samples", default="auto", help="N, or 'auto' to find the largest N that fits")
    p.add_argument("--frames", type=int, default=3000, help="real-time frames in the measured run (default 3000)")
    p.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    p.add_argument("--models", help="model folder (default: the shipped models/)")
    p.add_argument("--period-ms", type=float, default=10.0, help="CFS period for the quota (default 10 ms)")
    p.add_argument("--probe-frames", type=int, default=600, help="real-time frames per N while searching (auto)")
    p.add_argument("--max-samples", type=int, default=128, help="largest N the auto search tries (default 128)")
    p.add_argument("--headroom", type=float, default=0.2, help="budget headroom (default 0.2 = 20 %%)")
    p.add_argument("--no-cgroup", action="store_true", help="do not try a cgroup quota (pin to one core only)")
    p.add_argument("--adaptive", action="store_true",
                   help="let the deadline watchdog (edge.governor) lower and raise N during the run; "
                        "--samples (or the auto choice) is the largest N")
    p.add_argument("--hog-at", type=float, default=None, metavar="SECONDS",
                   help="start a CPU hog this far into the measured run: busy processes on the pipeline's "
                        "core, outside its cgroup (a contended board)")
    p.add_argument("--hog-seconds", type=float, default=30.0, help="how long the hog runs (default 30 s)")
    p.add_argument("--hog-procs", type=int, default=4, help="busy processes in the hog (default 4)")
    p.add_argument("--quick", action="store_true",
                   help="an answer in under a minute: 120 probe frames per N up to N=64, then 600 measured frames")
    p.add_argument("--refine-steps", type=int, default=2, metavar="K",
                   help="the most refinement steps a frame: measure with a live target refined every frame (a "
                        "headset's TARGET at its worst) and choose N and K together along the governor's rungs "
                        "(default 2, as [refine] steps; 0: no target, N alone)")
    p.add_argument("--json", required=True, help="write the profile here")


# ---------------------------------------------------------------------------------------------- cgroup

class Feeder:
    """The bundled sample's tracker signals, looped, queued on the simulator's bench as the board's
    sources would deliver them (sim://feed): one headset report and one waist IMU sample per frame.
    The service reads them through its own links, synchroniser and calibration."""

    def __init__(self, hz, bench):
        import numpy as np
        from edgetools.sim import scheme
        from motion.takes import from_sample
        from firmware_bridge.samples import HeadsetSample, TrackerSample
        take = from_sample(SAMPLE)
        s = take.signals
        self.T, self.hz, self.now = take.frames, hz, 0.0
        self.headset = [HeadsetSample(0.0, s.head_pos[i], s.head_rot[i], s.hand_pos[i], s.hand_rot[i],
                                      np.ones(2, bool)) for i in range(self.T)]
        self.waist = [TrackerSample("waist", 0.0, s.waist_rot[i]) for i in range(self.T)]
        self.queues = {}
        for name in ("headset", "waist"):
            device = scheme.BenchDevice(clock=lambda: self.now)
            scheme.BENCH[f"{bench}-{name}"] = device
            self.queues[name] = device.queue
        self.bench = bench

    def urls(self):
        return f"sim://feed/{self.bench}-headset", f"sim://feed/{self.bench}-waist?tracker=waist"

    def frame(self, k):
        """Queue frame k's samples; returns its time on the service's clock (k / hz)."""
        t = self.now = k / self.hz
        h, w = self.headset[k % self.T], self.waist[k % self.T]
        h.t = w.t = t
        self.queues["headset"].append(h)
        self.queues["waist"].append(w)
        return t

    def close(self):
        from edgetools.sim import scheme
        for name in ("headset", "waist"):
            scheme.BENCH.pop(f"{self.bench}-{name}", None)


def _pct(a):
    import numpy as np
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]          # frames skipped for lateness have no compute time
    if not len(a):
        return {"p50": None, "p99": None, "max": None}
    return {"p50": round(float(np.median(a)), 4), "p99": round(float(np.percentile(a, 99)), 4),
            "max": round(float(a.max()), 4)}


def host_stalls(resp, cpu, period, quota=1.0, enforced=False, cfs_period=0.01):
    """Which late frames (resp > period, seconds) the host made late: their own CPU time `cpu` would
    have been done in time at the quota (cpu / quota plus one throttled CFS period where the quota is
    enforced; cpu alone where it is not). Skipped frames (cpu NaN) take the cause of the last frame
    measured before them. -> (stall [F] bool, own [F] bool): the late frames split by cause."""
    import numpy as np
    resp, cpu = np.asarray(resp, float), np.asarray(cpu, float)
    late = resp > period
    need = cpu / quota + (1.0 - quota) * cfs_period if enforced else cpu
    stall = late & (need <= period)
    skipped = ~np.isfinite(cpu)
    if skipped.any():
        measured = np.where(~skipped, np.arange(len(cpu)), -1)
        last = np.maximum.accumulate(measured)              # the last measured frame at or before each one
        cause = np.where(last >= 0, stall[np.maximum(last, 0)], True)
        stall = np.where(skipped, late & cause, stall)
    return stall, late & ~stall


class RunDelay:
    """The calling thread's time spent runnable but waiting for a CPU, in seconds
    (/proc/self/task/TID/schedstat's second field), read with one pread; 0 where the kernel has none."""

    def __init__(self):
        try:
            self.fd = os.open(f"/proc/self/task/{threading.get_native_id()}/schedstat", os.O_RDONLY)
        except OSError:
            self.fd = None

    def __call__(self):
        if self.fd is None:
            return 0.0
        try:
            return int(os.pread(self.fd, 128, 0).split()[1]) / 1e9
        except (OSError, IndexError, ValueError):
            return 0.0

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def steal_seconds():
    """The machine's stolen time so far (/proc/stat's steal column, all CPUs), in seconds; 0 where absent."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK") if len(fields) > 8 else 0.0
    except (OSError, ValueError):
        return 0.0


class CoreNeighbours:
    """How much of the profiled core other tasks used while the worker ran: the core's busy time less
    the worker's own (its process and the children it waited for). On a VM whose kernel charges
    interrupt work to the running task (no IRQ time accounting, as here), another process's memory
    traffic on the core shows up as the frame's own CPU time: a neighbour allocating and freeing
    512 MB in a loop, at nice 19, made frames of 22-26 ms of CPU out of 1.2 (#55). A profile to deploy
    from is made on a quiet core."""

    WARN_SHARE = 0.02

    def __init__(self, core):
        self.core = core

    def __enter__(self):
        self.busy0, self.wall0 = busy_seconds(self.core), time.monotonic()
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        self.own0 = r.ru_utime + r.ru_stime
        return self

    def __exit__(self, *exc):
        busy, r = busy_seconds(self.core), resource.getrusage(resource.RUSAGE_CHILDREN)
        self.wall = time.monotonic() - self.wall0
        self.other_s = None if busy is None or self.busy0 is None else max(
            0.0, (busy - self.busy0) - (r.ru_utime + r.ru_stime - self.own0))
        return False

    def report(self):
        share = None if self.other_s is None else self.other_s / max(self.wall, 1e-9)
        return {"core": self.core, "other_cpu_s": None if self.other_s is None else round(self.other_s, 2),
                "share": None if share is None else round(share, 4)}


def board_service(cfg, samples, feeder, steps):
    """The board's Service on the feeder's sim:// sources, as `edge run` builds it (no adaptive N:
    the profiler steers N itself from the release-to-done times), refining `steps` a frame (of at
    most cfg['refine_steps'])."""
    from firmware_bridge import config as config_mod
    from firmware_bridge.service import Service
    headset, waist = feeder.urls()
    runtime = {"samples": samples, "adaptive": False, "precision": cfg["precision"], "hz": cfg["hz"]}
    if cfg.get("models"):
        runtime["models"] = cfg["models"]
    k = cfg.get("refine_steps", 0)
    refine = {"steps": k} if k else {"enabled": False}
    raw = {"headset": {"url": headset}, "trackers": [{"url": waist}], "output": {"pose_stream": "headset"},
           "runtime": runtime, "refine": refine}
    if cfg.get("body"):             # a user's [body] (their height and legs: the poses sent on their limbs)
        raw["body"] = cfg["body"]
    board = config_mod.from_dict(raw, "edge profile")
    service = Service(board, clock=lambda: feeder.now, status=None, threaded=False)   # the feed is in-process
    service.pipeline.set_refine_steps(steps)
    return service


def paced_run(cfg, samples, frames, bar_desc, adaptive=False, hog=None, steps=None):
    """Real-time frames at cfg['hz'] through the board service's tick (sources -> sync -> calibration ->
    Pipeline.step -> POSE_FRAME), paced by the service's Pacer. Returns (stats, pipeline).

    steps: refinement steps a frame (default cfg['refine_steps']); with cfg['refine_steps'] > 0 a
    target is live every frame. adaptive: edge.governor picks N and K after every frame (samples and
    cfg['refine_steps'] are the largest). hog: (first frame, frames, processes) of a CPU hog during
    the measured frames."""
    run = PacedRun(cfg, samples, frames, adaptive, hog, steps)
    try:
        run.warm_up()
        run.measure(bar_desc)
    finally:                 # never leave busy processes behind, whatever happened
        run.close()
    return run.stats(), run.pipe


class PacedRun:
    """One paced run's service, feeder, hog and per-frame records (paced_run)."""

    WARM = 60               # frames: one second, paced like the run, not counted

    def __init__(self, cfg, samples, frames, adaptive, hog, steps):
        import numpy as np
        from edge.governor import SampleGovernor
        from edge.pipeline import STAGES
        from firmware_bridge.links import Pacer
        self.cfg, self.samples, self.frames, self.adaptive, self.hog = cfg, samples, frames, adaptive, hog
        self.period = 1.0 / cfg["hz"]
        self.feeder = Feeder(cfg["hz"], f"profile{os.getpid()}-{samples}-{frames}")
        self.steps = cfg.get("refine_steps", 0) if steps is None else steps
        self.service = board_service(cfg, samples, self.feeder, self.steps)
        self.pipe = self.service.pipeline
        self.hog_proc = Hog(hog[2], cfg.get("cgroup_root")) if hog else None
        self.clock, self.cpu_clock = time.perf_counter, time.thread_time
        self.pacer = Pacer(cfg["hz"], self.clock)
        self.resp, self.comp, self.cpu, self.wait = (np.full(frames, np.nan) for _ in range(4))
        self.run_delay, self.steal = RunDelay(), 0.0
        self.in_loop = {k: np.full(frames, np.nan) for k in ("sync", "pipeline_step", "output_encoding")}
        self.stage_cpu = np.full((frames, len(STAGES)), np.nan)
        self.live_n, self.live_k = np.empty(frames, np.int32), np.empty(frames, np.int32)
        self.governor = (SampleGovernor(1000.0 * self.period, samples, max_steps=cfg.get("refine_steps", 0))
                         if adaptive else None)
        self.misses = self.late_starts = self.skipped = 0
        self.refined_before = 0

    def tick(self, k):
        self.service.step(self.feeder.frame(k))        # poll the sources, then tick

    def warm_up(self):
        pipe = self.pipe
        self.pacer.start()
        for k in range(self.WARM):
            self.pacer.wait()
            self.tick(k)
            if k == self.WARM // 2 and pipe.refiner is not None:
                # A target that never ends, 45 cm from the left toe: refined every frame from here, so the
                # refiner's first frame (its sessions' first calls: 0.7 ms of CPU against 0.3 after)
                # falls in the warm-up, not in the measured frames.
                from edge.skeleton import JOINT
                pipe.refiner.add_target("l_toe", pipe.out.positions[JOINT["l_toe"]] + [0.0, 0.4, 0.2], radius=0.0,
                                        first=0, last=1 << 40)
        self.refined_before = pipe.refiner.applied if pipe.refiner else 0     # the warm-up's are not counted

    def measure(self, bar_desc):
        from edge.progress import Progress
        pipe, hog, frames = self.pipe, self.hog, self.frames
        pipe.timing = True
        self.steal = -steal_seconds()
        with Progress(frames, bar_desc) as bar:
            i = 0
            while i < frames:
                if self.hog_proc and i == hog[0]:
                    self.hog_proc.start()
                elif self.hog_proc and i == hog[0] + hog[1]:
                    self.hog_proc.stop()
                release, late = self.pacer.wait()
                self._skip(i, late, release)
                i += late
                if i >= frames:
                    break
                self._frame(i, release)
                if i % 30 == 29 or i == frames - 1:
                    # cheap on purpose: this runs inside the measured process between frames
                    bar.update(30 if i % 30 == 29 else (i % 30) + 1, postfix=f"N={pipe.samples} K={self.live_k[i]} "
                               f"last {self.resp[i] * 1e3:.2f} ms misses {self.misses}")
                i += 1
        self.steal += steal_seconds()
        pipe.timing = False

    def _live(self, j):
        refiner = self.pipe.refiner
        self.live_n[j], self.live_k[j] = self.pipe.samples, refiner.steps if refiner else 0

    def _skip(self, i, late, release):
        """Frames whose deadline passed before they could start: skipped and missed, as `edge run` does
        (a late service resynchronises to the next tick instead of bursting)."""
        for j in range(i, min(i + late, self.frames)):
            self._live(j)
            self.resp[j] = self.clock() - (release - (i + late - j) * self.period)
            self.skipped += 1
            self.misses += 1

    def _frame(self, i, release):
        import numpy as np
        clock, cpu_clock = self.clock, self.cpu_clock
        now = clock()
        self.late_starts += 1 if now > release + 0.001 else 0
        self._live(i)
        ca, wa = cpu_clock(), self.run_delay()
        self.tick(self.WARM + i)
        d, cd, self.wait[i] = clock(), cpu_clock(), self.run_delay() - wa
        st = self.in_loop
        st["sync"][i], st["pipeline_step"][i], st["output_encoding"][i] = np.diff(self.service.tick_marks)
        self.stage_cpu[i] = np.diff(self.pipe.stage_ns) / 1e6
        self.resp[i], self.comp[i], self.cpu[i] = d - release, d - now, cd - ca
        self.misses += 1 if self.resp[i] > self.period else 0
        if self.governor is not None:
            self.governor.steer(self.pipe, self.resp[i] * 1e3)

    def close(self):
        self.run_delay.close()
        if self.hog_proc:
            self.hog_proc.reap()
        self.service.close()
        self.feeder.close()

    def stats(self):
        import numpy as np
        from edge.pipeline import STAGES
        pipe = self.pipe
        ms = lambda x: x * 1e3  # noqa: E731
        cfg = self.cfg
        stall, own = host_stalls(self.resp, self.cpu, self.period, cfg.get("quota", 1.0), cfg.get("enforced", False),
                                 cfg.get("period_ms", 10.0) / 1e3)
        stats = {"samples": self.samples, "refine_steps": self.steps, "frames": self.frames,
                 "deadline_misses": self.misses, "own_misses": int(own.sum()), "host_stalls": int(stall.sum()),
                 "late_starts": self.late_starts, "skipped_frames": self.skipped,
                 "frame_ms": _pct(ms(self.resp)), "frame_ms_own": _pct(ms(self.resp[~stall])),
                 "compute_ms": _pct(ms(self.comp)), "cpu_ms": _pct(ms(self.cpu)),
                 "host": {"stall_frames": int(stall.sum()), "stalled_frame_ms": _pct(ms(self.resp[stall])),
                          "stalled_frames_cpu_ms": _pct(ms(self.cpu[stall])),
                          "wait_to_run_ms": _pct(ms(self.wait)), "stalled_frames_wait_to_run_ms": _pct(ms(self.wait[stall])),
                          "steal_s": round(self.steal, 3),
                          "stalls_at": [int(j) for j in np.flatnonzero(stall)[:50]]},
                 "stages_in_loop_ms": {k: _pct(ms(v)) for k, v in self.in_loop.items()},
                 "stages_cpu_ms": {name: _pct(self.stage_cpu[:, k]) for k, name in enumerate(STAGES)},
                 "ssi_switches": pipe.switch_count,
                 "refined_frames": pipe.refiner.applied - self.refined_before if pipe.refiner else 0}
        if self.adaptive or self.hog:
            stats["contention"] = contention_report(self.resp, self.live_n, self.period, self.hog, self.governor,
                                                    self.live_k)
        return stats


def _timeline(values):
    """[[frame, value], ...] at frame 0 and wherever the value changes."""
    import numpy as np
    changes = np.flatnonzero(np.diff(values)) + 1
    return [[0, int(values[0])]] + [[int(i), int(values[i])] for i in changes]


def contention_report(resp, live_n, period, hog, governor, live_k):
    """Deadline misses and N (and K) before, during and after the hog, and when they changed."""
    late = resp > period
    phases = {"whole": slice(0, len(resp))}
    if hog:
        a, b = hog[0], min(hog[0] + hog[1], len(resp))
        phases.update(before=slice(0, a), during=slice(a, b), after=slice(b, len(resp)))
    out = {"phases": {}}
    for name, sl in phases.items():
        n, m = live_n[sl], late[sl]
        if len(n):
            out["phases"][name] = {"frames": int(len(n)), "deadline_misses": int(m.sum()),
                                   "miss_rate": round(float(m.mean()), 5), "samples_mean": round(float(n.mean()), 2),
                                   "samples_min": int(n.min()), "samples_max": int(n.max()),
                                   "samples_last": int(n[-1]), "refine_steps_min": int(live_k[sl].min()),
                                   "refine_steps_last": int(live_k[sl][-1]), "frame_ms": _pct(resp[sl] * 1e3)}
    out["samples_timeline"], out["refine_steps_timeline"] = _timeline(live_n), _timeline(live_k)
    out["frame_ms_per_frame"] = [round(float(x), 2) for x in resp * 1e3]     # for `edge report`
    out["period_ms"] = 1e3 * period
    if hog:
        out["hog"] = {"start_frame": hog[0], "frames": hog[1], "processes": hog[2]}
    if governor is not None:
        out["governor"] = {"changes": [list(c) for c in governor.changes], "final_hold_frames": governor.hold,
                           "high_ms": governor.high_ms, "low_ms": governor.low_ms}
    return out


STALLS = 2      # late frames in a measured run that can be the machine's own stalls, not N's cost
PROBE_STALLS = 1    # the same for a probe (a fifth of a measured run's frames)


def probe_fits(st, budget):
    """Whether a probe's rung fits, on the frames' own cost: the p99 of the frames the host did not stall
    (frame time, or CPU time where the quota is modelled) within the budget, and at most PROBE_STALLS
    frames late of their own (a borderline frame is not a verdict: the measured run that follows is,
    and steps down if it misses). The host's stalls (host_stalls) are reported, never counted."""
    v = st.get("frame_ms_own", st["frame_ms"])["p99"] if budget["metric"].startswith("frame") else st["cpu_ms"]["p99"]
    return v is not None and v <= budget["ms"] and st.get("own_misses", st["deadline_misses"]) <= PROBE_STALLS


def next_run(ladder, runs, most=6):
    """The rung the measured run goes to after `runs` (the measured runs so far, in order), or None when
    the last one stands: it met every deadline, it is the ladder's first rung, or `most` runs were made.
    A run with at most STALLS late frames is made once more at the same rung before stepping down: one
    stall of the machine is not a verdict on N (as a failed probe is repeated once). More late frames,
    or a second miss at the rung, step down one rung."""
    last = runs[-1]
    rung = (last["samples"], last["refine_steps"])
    misses = last.get("own_misses", last["deadline_misses"])       # the host's stalls are not N's
    if misses == 0 or rung == ladder[0] or len(runs) >= most:
        return None
    again = len(runs) >= 2 and (runs[-2]["samples"], runs[-2]["refine_steps"]) == rung
    if misses <= STALLS and not again:
        return rung
    return ladder[ladder.index(rung) - 1]


def worker(cfg):
    import numpy as np  # noqa: F401  (imported before the clock starts)
    hz = cfg["hz"]
    frame_budget_ms = 1000.0 / hz
    q = cfg["quota"]
    enforced = cfg["enforced"]
    head = 1.0 - cfg["headroom"]
    if enforced or q >= 1.0:
        budget = {"metric": "frame_ms_own.p99 (release to done, quota in effect, host stalls apart)",
                  "ms": head * frame_budget_ms}
    else:
        budget = {"metric": "cpu_ms.p99 against the quota share (modelled, quota not enforced)",
                  "ms": head * q * frame_budget_ms}

    # The (N, K) rungs the governor moves along (edge.governor.rungs), cheapest first.
    ladder = rungs(cfg["max_samples"], cfg.get("refine_steps", 0))
    probes = []
    if cfg["samples"] == "auto":
        best = None
        for n, k in ladder:
            for _attempt in range(2):          # a failed probe is repeated once: one busy second is not a verdict
                st, _ = paced_run(cfg, n, cfg["probe_frames"], f"probe N={n:<3d} K={k}", steps=k)
                st["fits"] = probe_fits(st, budget)
                probes.append({key: st[key] for key in ("samples", "refine_steps", "frames", "deadline_misses",
                                                        "own_misses", "host_stalls", "frame_ms", "frame_ms_own",
                                                        "cpu_ms", "fits")})
                if st["fits"]:
                    break
            if not st["fits"]:
                break
            best = (n, k)
        chosen = best or ladder[0]
    else:       # a fixed N, with the most steps the ladder gives it
        chosen = max(r for r in rungs(int(cfg["samples"]), cfg.get("refine_steps", 0)) if r[0] == int(cfg["samples"]))
    attempts = []
    hog = None
    if cfg.get("hog_at") is not None:
        hog = (int(round(cfg["hog_at"] * hz)), int(round(cfg["hog_seconds"] * hz)), cfg["hog_procs"])
    adaptive = bool(cfg.get("adaptive"))
    while True:
        n, k = chosen
        st, pipe = paced_run(cfg, n, cfg["frames"], f"run N={n:<3d} K={k}", adaptive, hog, steps=k)
        attempts.append({key: st[key] for key in ("samples", "refine_steps", "frames", "deadline_misses", "own_misses",
                                                  "host_stalls", "frame_ms", "frame_ms_own", "cpu_ms")})
        # Adaptive or contended runs are reported as they went: stepping down would hide the verdict.
        if cfg["samples"] != "auto" or adaptive or hog:
            break
        after = next_run(ladder, attempts)
        if after is None:
            break
        chosen = after
    stages = {"sync": st["stages_in_loop_ms"]["sync"], "pipeline_step": st["stages_in_loop_ms"]["pipeline_step"],
              "output_encoding": st["stages_in_loop_ms"]["output_encoding"]}
    stages.update(st["stages_cpu_ms"])
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    with open("/proc/self/statm") as f:
        rss_now = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    return {"chosen_samples": chosen[0], "chosen_refine_steps": chosen[1], "frames": st["frames"], "frame_ms": st["frame_ms"], "compute_ms": st["compute_ms"],
            "cpu_ms": st["cpu_ms"], "deadline_misses": st["deadline_misses"], "own_misses": st["own_misses"],
            "host_stalls": st["host_stalls"], "host": st["host"], "frame_ms_own": st["frame_ms_own"],
            "late_starts": st["late_starts"],
            "skipped_frames": st["skipped_frames"],
            "ssi_switches": st["ssi_switches"], "refined_frames": st["refined_frames"], "stages": stages,
            "rss_mb": round(rss_now, 1),
            "rss_peak_mb": round(rss, 1), "budget": budget, "frame_budget_ms": frame_budget_ms,
            "probes": probes, "runs": attempts, "core": sorted(os.sched_getaffinity(0)),
            "compiled_core": pipe.native is not None,
            "precision_in_use": pipe.precision, "precision_note": pipe.precision_note,
            "int8_check": pipe.manifest["int8_check"],
            "contention": st.get("contention")}


STAGE_METHODS = {
    "sync": "every frame, wall time: Service.tick's FrameSynchronizer.frame (the sources were read by Service.poll)",
    "pipeline_step": "every frame, wall time: Service.tick's calibration + Pipeline.step as a whole",
    "output_encoding": "every frame, wall time: Service._emit (quat.from_matrix + POSE_FRAME encoding and send)",
    "features": "every frame, thread CPU time, inside the live Pipeline.step (pipe.timing): the frame's inputs "
                "(ep_frame_inputs with the compiled core)",
    "decoder": "inside the live step: the decoder's ONNX Runtime call (N+1 rows, IOBinding) and its finite check",
    "poses": "inside the live step: FK, foot locks, IK and the ring copies of every row (ep_frame_poses)",
    "criteria": "inside the live step: the selection cost of the N samples (autoencoder and physical plausibility; "
                "N>1 only)",
    "selection": "inside the live step: the SSI decision (ep_switch_to) and, on a switch, the batched "
                 "transition recompute",
    "emit": "inside the live step: the shown row's pose made again from the ring (ep_emit)",
}


def _worker_main(cfg_path, out_path):
    cfg = json.loads(Path(cfg_path).read_text())
    try:
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
    except (AttributeError, OSError):
        pass
    Path(out_path).write_text(json.dumps(worker(cfg)))
    return 0


# ---------------------------------------------------------------------------------------------- main

def main(args):
    if args.quick:              # a first look; the full run (the defaults) is what to deploy with
        args.probe_frames, args.frames, args.max_samples = 120, 600, min(args.max_samples, 64)
    if args.samples != "auto":
        try:
            n = int(args.samples)
        except ValueError:
            print(f"edge profile: --samples must be a number or 'auto', not {args.samples!r}", file=sys.stderr)
            return 2
        if not 1 <= n <= 128:
            print("edge profile: --samples must be 1..128", file=sys.stderr)
            return 2
    quota = 1.0 if args.cpu_quota is None else args.cpu_quota
    if not 0.01 <= quota <= 1.0:
        print("edge profile: --cpu-quota is a fraction of one core, 0.01..1", file=sys.stderr)
        return 2
    if not 0 <= args.refine_steps <= 8:
        print("edge profile: --refine-steps must be 0..8", file=sys.stderr)
        return 2
    if args.hz <= 0 or args.frames < 1:
        print("edge profile: --hz and --frames must be positive", file=sys.stderr)
        return 2
    from edge.inference import model_files
    from edge.modelfiles import DEFAULT_DIR, ModelError, load_manifest
    try:                                      # fail early, with the fix, before any cgroup is made
        folder = Path(args.models) if args.models else DEFAULT_DIR
        load_manifest(folder, need=model_files(args.precision, load_manifest(folder, need=())))
    except ModelError as e:
        print(f"edge profile: {e}", file=sys.stderr)
        return 2
    # Stopped by SIGTERM (systemd, timeout, kill) as by Ctrl-C: the worker is killed and the cgroup removed.
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm) if _main_thread() else None
    try:
        return _profile(args, quota)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main_thread():
    return threading.current_thread() is threading.main_thread()


def _exit_on_sigterm(signum, frame):
    raise SystemExit(128 + signum)


def _profile(args, quota):
    limit = CpuLimit(quota, args.period_ms * 1000, disabled=args.no_cgroup)
    cfg = {"hz": args.hz, "quota": quota, "enforced": limit.enforced, "samples": args.samples, "frames": args.frames,
           "probe_frames": args.probe_frames, "max_samples": args.max_samples, "headroom": args.headroom, "precision": args.precision,
           "models": args.models, "adaptive": args.adaptive, "hog_at": args.hog_at, "hog_seconds": args.hog_seconds,
           "hog_procs": args.hog_procs, "cgroup_root": str(limit.path.parent) if limit.enforced else None,
           "refine_steps": args.refine_steps, "period_ms": args.period_ms}
    print(f"edge profile: {args.hz:g} Hz, CPU {quota:g} of one core "
          f"({'cgroup quota ' + str(limit.quota_us) + ' us per ' + str(limit.period_us) + ' us' if limit.enforced else 'quota NOT enforced: ' + limit.why}), "
          f"samples {args.samples}, {args.frames} frames"
          + (f", a target live every frame, refined up to {args.refine_steps} steps" if args.refine_steps
             else ", no target"), file=sys.stderr)
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(root)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    t0 = time.time()
    try:
        with tempfile.TemporaryDirectory(prefix="edge-profile-") as tmp:
            cfg_path, out_path = Path(tmp) / "cfg.json", Path(tmp) / "out.json"
            cfg_path.write_text(json.dumps(cfg))
            before = limit.stats()
            with CoreNeighbours(min(os.sched_getaffinity(0))) as neighbours:     # the core the worker pins to
                proc = subprocess.run([sys.executable, "-m", "edgetools.profile", "--worker", str(cfg_path),
                                       str(out_path)], env=env, preexec_fn=limit.join if limit.enforced else None)
            after = limit.stats()
            if proc.returncode != 0 or not out_path.exists():
                print(f"edge profile: the worker failed (exit {proc.returncode})", file=sys.stderr)
                return 1
            res = json.loads(out_path.read_text())
    finally:
        limit.cleanup()
    throttled = {k: round(after[k] - before.get(k, 0), 3) for k in after} if after else None
    result = {"hz": args.hz, "precision": args.precision, "samples_requested": args.samples,
              "refine_steps": args.refine_steps,
              "cpu_quota": {**limit.describe(), "throttling": throttled}, "quota_enforced": limit.enforced,
              "chosen_samples": res["chosen_samples"], "chosen_refine_steps": res["chosen_refine_steps"],
              "frames": res["frames"],
              "deadline_misses": res["deadline_misses"], "own_misses": res["own_misses"],
              "host_stalls": res["host_stalls"], "host": res["host"], "frame_ms": res["frame_ms"],
              "frame_ms_own": res["frame_ms_own"],
              "compute_ms": res["compute_ms"], "cpu_ms": res["cpu_ms"], "late_starts": res["late_starts"],
              "skipped_frames": res["skipped_frames"],
              "rss_mb": res["rss_mb"], "rss_peak_mb": res["rss_peak_mb"], "stages": res["stages"],
              "stage_methods": {k: STAGE_METHODS[k] for k in res["stages"]},
              "budget": {**res["budget"], "frame_period_ms": res["frame_budget_ms"], "headroom": args.headroom},
              "probes": res["probes"], "runs": res["runs"], "ssi_switches": res["ssi_switches"],
              "refined_frames": res["refined_frames"],
              "pinned_core": res["core"], "compiled_core": res["compiled_core"],
              "core_neighbours": neighbours.report(),
              # what ran: int8 falls back to fp32 where its start-up self-check fails (edge.int8check)
              "precision_in_use": res["precision_in_use"], "precision_note": res["precision_note"],
              "int8_check": res["int8_check"],
              "input": f"{SAMPLE.name} signals looped, through FrameSynchronizer",
              "seconds": round(time.time() - t0, 1)}
    if res.get("contention"):
        result["adaptive"] = args.adaptive
        result["contention"] = res["contention"]
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    fm = result["frame_ms"]
    print(f"chosen_samples={result['chosen_samples']} chosen_refine_steps={result['chosen_refine_steps']} "
          f"frames={result['frames']} deadline_misses={result['deadline_misses']} "
          f"(own {result['own_misses']}, host stalls {result['host_stalls']}, steal {result['host']['steal_s']:g} s) "
          f"frame_ms p50={fm['p50']:.2f} p99={fm['p99']:.2f} cpu_ms p99={result['cpu_ms']['p99']:.2f} "
          f"rss_mb={result['rss_mb']} quota_enforced={str(limit.enforced).lower()} "
          f"precision={result['precision_in_use']}" + (f" ({result['precision_note']})" if result["precision_note"] else ""))
    for name, ph in (result.get("contention") or {}).get("phases", {}).items():
        print(f"  {name:>6}: {ph['frames']} frames, deadline misses {ph['deadline_misses']} ({100 * ph['miss_rate']:.2f} %), "
              f"N mean {ph['samples_mean']:g} (min {ph['samples_min']}, last {ph['samples_last']}), "
              f"frame p99 {ph['frame_ms']['p99']:.2f} ms")
    near = result["core_neighbours"]
    if near["share"] is not None and near["share"] > CoreNeighbours.WARN_SHARE:
        print(f"edge profile: other tasks used {100 * near['share']:.0f} % of core {near['core']} during the run; "
              "their memory traffic can be charged to the frame's own CPU time (a page-churning neighbour at "
              "nice 19 made 26 ms frames of 1.2): profile on a quiet core before deploying its N", file=sys.stderr)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--worker":
        sys.exit(_worker_main(sys.argv[2], sys.argv[3]))
    import argparse
    _ap = argparse.ArgumentParser(prog="python -m edgetools.profile", description=__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(_ap)
    sys.exit(main(_ap.parse_args()))
