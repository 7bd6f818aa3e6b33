"""CPU limits for `edge profile`: a cgroup CFS quota for the measured worker (v1 `cpu` or v2), and
busy processes on its core outside that group (Hog), the way another service would contend."""
import os
import time
import subprocess
import sys
from pathlib import Path

CGROUP_V1 = Path("/sys/fs/cgroup/cpu")
CGROUP_V2 = Path("/sys/fs/cgroup")


def _v2_has_cpu():
    ctl = CGROUP_V2 / "cgroup.controllers"
    return ctl.exists() and "cpu" in ctl.read_text().split()


class CpuLimit:
    """A child cgroup with a CFS quota, or nothing (then `enforced` is False and `why` says why)."""

    def __init__(self, fraction, period_us, disabled=False):
        self.fraction, self.period_us = fraction, int(period_us)
        self.quota_us = max(1000, int(round(fraction * self.period_us))) if fraction < 1.0 else -1
        self.path, self.version, self.enforced, self.why = None, None, False, ""
        if fraction >= 1.0:
            self.why = "no quota requested (a whole core)"
            return
        if disabled:
            self.why = "--no-cgroup"
            return
        if os.geteuid() != 0:
            self.why = "not root: cannot create a cgroup"
            return
        name = f"edgepose-profile-{os.getpid()}"
        try:
            if (CGROUP_V1 / "cpu.cfs_quota_us").exists():
                self.path, self.version = CGROUP_V1 / name, 1
                self.path.mkdir()
                (self.path / "cpu.cfs_period_us").write_text(str(self.period_us))
                (self.path / "cpu.cfs_quota_us").write_text(str(self.quota_us))
            elif _v2_has_cpu():
                ctl = CGROUP_V2 / "cgroup.subtree_control"
                if "cpu" not in ctl.read_text().split():
                    ctl.write_text("+cpu")
                self.path, self.version = CGROUP_V2 / name, 2
                self.path.mkdir()
                (self.path / "cpu.max").write_text(f"{self.quota_us} {self.period_us}")
            else:
                self.why = "no cgroup cpu controller found (v1 /sys/fs/cgroup/cpu or v2 cpu.max)"
                return
            self.enforced = True
        except OSError as e:
            self.why = f"cgroup not writable: {e}"
            self.cleanup()

    def join(self):
        """Runs in the worker (preexec_fn, before exec): move this process into the group."""
        if self.enforced:
            (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def stats(self):
        if not self.enforced:
            return {}
        try:
            raw = dict(line.split() for line in (self.path / "cpu.stat").read_text().splitlines())
        except OSError:
            return {}
        if self.version == 1:
            return {"nr_periods": int(raw.get("nr_periods", 0)), "nr_throttled": int(raw.get("nr_throttled", 0)),
                    "throttled_ms": int(raw.get("throttled_time", 0)) / 1e6}
        return {"nr_periods": int(raw.get("nr_periods", 0)), "nr_throttled": int(raw.get("nr_throttled", 0)),
                "throttled_ms": int(raw.get("throttled_usec", 0)) / 1e3}

    def describe(self):
        return {"fraction": self.fraction, "period_us": self.period_us,
                "quota_us": self.quota_us if self.quota_us > 0 else None,
                "cgroup": str(self.path) if self.enforced else None,
                "cgroup_version": self.version if self.enforced else None,
                "why_not_enforced": None if self.enforced else self.why}

    def cleanup(self):
        if self.path is not None and self.path.exists():
            for _ in range(50):                      # the worker has exited; its removal may lag a moment
                try:
                    self.path.rmdir()
                    return
                except OSError:
                    time.sleep(0.05)


# ---------------------------------------------------------------------------------------------- worker


class Hog:
    """Busy-looping processes started on cue: other software on the board wanting the same core.

    Spawned before the clock starts (blocked on a pipe) so no fork lands in a measured frame. They
    share the worker's core but not its cgroup (each moves itself to the root group before exec), so
    they take CPU from it the way another service would: CFS splits the core between the worker's
    group and each hog by weight, and the worker keeps whichever is smaller, that or its quota."""

    def __init__(self, procs, cgroup_root=None):
        def leave_group():
            if cgroup_root:
                Path(cgroup_root, "cgroup.procs").write_text(str(os.getpid()))
        # Spins until the worker goes away, even if it is killed before it can stop them. The worker's pid
        # is passed in, not read in the child: a worker that died while the child was starting would
        # otherwise leave it spinning under its new parent for good.
        code = "import os, sys; p = int(sys.argv[1]); sys.stdin.read(1)\nwhile os.getppid() == p:\n    sum(range(10000))"
        self.procs = [subprocess.Popen([sys.executable, "-c", code, str(os.getpid())], stdin=subprocess.PIPE,
                                       preexec_fn=leave_group)
                      for _ in range(procs)]

    def start(self):
        for p in self.procs:
            p.stdin.write(b"x")
            p.stdin.flush()

    def stop(self):
        for p in self.procs:
            p.kill()

    def reap(self):
        self.stop()
        for p in self.procs:
            p.wait()


def busy_seconds(core=None):
    """CPU time spent so far by every task, interrupts included (/proc/stat: user, nice, system, irq,
    softirq; not idle, iowait or steal), on one core or, with None, the whole machine, in seconds;
    None where the kernel has no such line."""
    key = "cpu " if core is None else f"cpu{core} "
    try:
        with open("/proc/stat") as f:
            for line in f:
                if line.startswith(key):
                    v = [int(x) for x in line.split()[1:8]]
                    return (v[0] + v[1] + v[2] + v[5] + v[6]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError):
        pass
    return None
