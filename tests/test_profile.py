"""`edge profile` on tiny configurations: the JSON it writes, and an honest quota_enforced."""
import argparse
import json
import os
import time
from pathlib import Path

import pytest

from edgetools import profile

KEYS = ("stages", "frame_ms", "deadline_misses", "rss_mb", "cpu_quota", "quota_enforced", "chosen_samples",
        "stage_methods", "budget")
STAGES = ("sync", "pipeline_step", "features", "decoder", "poses", "criteria", "selection", "emit", "output_encoding")


def run(tmp_path, *argv):
    ap = argparse.ArgumentParser()
    profile.add_arguments(ap)
    out = tmp_path / "profile.json"
    args = ap.parse_args([*argv, "--json", str(out)])
    assert profile.main(args) == 0
    return json.loads(out.read_text())


def cgroup_possible():
    return os.geteuid() == 0 and os.access(profile.CGROUP_V1, os.W_OK) and (profile.CGROUP_V1 / "cpu.cfs_quota_us").exists()


def leftover_groups():
    return sorted(p.name for p in profile.CGROUP_V1.glob("edgepose-profile-*")) if profile.CGROUP_V1.exists() else []


def test_fixed_n_without_cgroup_writes_every_key_and_says_the_quota_was_not_enforced(tmp_path):
    r = run(tmp_path, "--cpu-quota", "0.5", "--samples", "2", "--frames", "20", "--no-cgroup")
    for k in KEYS:
        assert k in r
    assert r["quota_enforced"] is False and r["cpu_quota"]["why_not_enforced"] == "--no-cgroup"
    assert r["chosen_samples"] == 2 and r["frames"] == 20
    for s in STAGES:
        assert r["stages"][s]["p50"] is not None and s in r["stage_methods"]
    # The parts add up: the tick's own three parts fit in the measured frame (release to done), and the
    # live step's stages (thread CPU time) fit in the step's wall time; the decoder is a real share of it.
    tick = sum(r["stages"][s]["p50"] for s in ("sync", "pipeline_step", "output_encoding"))
    assert 0 < tick <= r["frame_ms"]["p50"] * 1.05
    inside = sum(r["stages"][s]["p50"] for s in ("features", "decoder", "poses", "criteria", "selection", "emit"))
    assert 0 < inside <= r["stages"]["pipeline_step"]["p99"] * 1.05
    assert r["stages"]["decoder"]["p50"] > 0.1 * inside
    assert 20 < r["rss_mb"] < 2000
    assert "modelled" in r["budget"]["metric"]


@pytest.mark.skipif(not cgroup_possible(), reason="needs root and a writable cgroup v1 cpu hierarchy")
def test_quota_runs_in_a_cgroup_that_is_removed_afterwards(tmp_path):
    before = leftover_groups()
    r = run(tmp_path, "--cpu-quota", "0.5", "--samples", "1", "--frames", "30", "--period-ms", "10")
    assert r["quota_enforced"] is True
    assert r["cpu_quota"]["quota_us"] == 5000 and r["cpu_quota"]["period_us"] == 10000
    assert r["cpu_quota"]["throttling"]["nr_periods"] > 0       # the kernel accounted the group's periods
    assert leftover_groups() == before


def test_a_profile_stopped_by_sigterm_removes_its_cgroup(tmp_path):
    """systemd, timeout or kill stop it with SIGTERM: the worker goes and so does the cgroup."""
    import signal
    import subprocess
    import sys
    import time
    if not profile.CpuLimit(0.5, 10000).enforced:
        pytest.skip("needs root and a writable cgroup cpu controller")
    before = leftover_groups()
    proc = subprocess.Popen([sys.executable, "-m", "edgecli", "profile", "--cpu-quota", "0.5", "--samples", "1",
                             "--frames", "100000", "--json", str(tmp_path / "p.json")], stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while leftover_groups() == before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert leftover_groups() != before, "the profile made its cgroup"
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 128 + signal.SIGTERM
    assert leftover_groups() == before


def test_the_profile_measures_frames_with_a_live_target_refined_k_steps(tmp_path):
    """--refine-steps K: every measured frame refines the shown sample against a target (a headset's
    TARGET at its worst), so the N chosen leaves room for it; 0 measures without."""
    with_target = run(tmp_path, "--samples", "2", "--frames", "30", "--no-cgroup", "--refine-steps", "1")
    # every measured frame that ran (a frame whose deadline passed before it could start is skipped)
    ran = 30 - with_target["skipped_frames"]
    assert with_target["refine_steps"] == 1 and with_target["refined_frames"] == ran >= 20
    without = run(tmp_path, "--samples", "2", "--frames", "30", "--no-cgroup", "--refine-steps", "0")
    assert without["refine_steps"] == 0 and without["refined_frames"] == 0


def test_auto_probes_the_rungs_and_chooses_a_probed_n_and_k(tmp_path):
    """--samples auto walks the governor's (N, K) rungs, cheapest first, with a target live every
    frame; the measured run starts at the highest rung that fitted."""
    from edge.governor import rungs
    r = run(tmp_path, "--samples", "auto", "--max-samples", "4", "--refine-steps", "2", "--frames", "15",
            "--probe-frames", "8", "--hz", "120", "--no-cgroup")
    ladder = rungs(4, 2)
    probed = [(p["samples"], p["refine_steps"]) for p in r["probes"]]
    order = [ladder.index(rung) for rung in probed]
    assert order == sorted(order) and order[0] == 0              # in ladder order, from the cheapest
    # The rule: the measured run starts at the highest rung that fitted when probed (the first if none
    # did) and steps down only after a run that missed deadlines; the reported N and K are the last run's.
    fitting = [ladder.index((p["samples"], p["refine_steps"])) for p in r["probes"] if p["fits"]]
    first = r["runs"][0]
    assert (first["samples"], first["refine_steps"]) == ladder[max(fitting) if fitting else 0]
    assert (r["chosen_samples"], r["chosen_refine_steps"]) == (r["runs"][-1]["samples"], r["runs"][-1]["refine_steps"])
    assert all(run["deadline_misses"] > 0 for run in r["runs"][:-1])


def test_not_root_is_reported_honestly(monkeypatch):
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    lim = profile.CpuLimit(0.25, 10000)
    assert not lim.enforced and "not root" in lim.why


def test_bad_arguments_are_refused(tmp_path, capsys):
    ap = argparse.ArgumentParser()
    profile.add_arguments(ap)
    assert profile.main(ap.parse_args(["--samples", "0", "--json", str(tmp_path / "x.json")])) == 2
    assert profile.main(ap.parse_args(["--cpu-quota", "2", "--json", str(tmp_path / "x.json")])) == 2
    assert not Path(tmp_path / "x.json").exists()


def hog_processes():
    out = []
    for p in Path("/proc").glob("[0-9]*"):
        try:
            if b"sum(range(10000))" in (p / "cmdline").read_bytes():
                out.append(p.name)
        except OSError:
            pass
    return out


def test_a_hog_run_reports_each_phase_and_leaves_no_busy_process_behind(tmp_path):
    r = run(tmp_path, "--samples", "8", "--adaptive", "--frames", "90", "--hog-at", "0.5", "--hog-seconds", "0.5",
            "--hog-procs", "2", "--no-cgroup")
    c = r["contention"]
    assert r["adaptive"] is True and c["hog"] == {"start_frame": 30, "frames": 30, "processes": 2}
    assert [c["phases"][p]["frames"] for p in ("before", "during", "after")] == [30, 30, 30]
    assert sum(c["phases"][p]["deadline_misses"] for p in ("before", "during", "after")) == r["deadline_misses"]
    assert c["samples_timeline"][0] == [0, 8] and "governor" in c
    # a killed process leaves /proc when it is reaped, which a busy machine can take a moment to do
    give_up = time.monotonic() + 3.0
    while hog_processes() and time.monotonic() < give_up:
        time.sleep(0.05)
    assert hog_processes() == []


def test_a_measured_run_that_misses_is_run_again_at_its_rung_before_stepping_down():
    """One or two late frames (a stall of the machine) do not cost a rung: the run is made once more at
    the same (N, K), and a second miss there steps down one rung; more late frames step down at once; a
    clean run, the first rung or the sixth run ends it."""
    from edge.governor import rungs
    ladder = rungs(128, 2)
    top, below = ladder[-1], ladder[-2]

    def runs(*rows):
        return [{"samples": n, "refine_steps": k, "deadline_misses": m} for (n, k), m in rows]

    assert profile.next_run(ladder, runs((top, 0))) is None
    assert profile.next_run(ladder, runs((top, 1))) == top
    assert profile.next_run(ladder, runs((top, 1), (top, 0))) is None
    assert profile.next_run(ladder, runs((top, 1), (top, 2))) == below
    assert profile.next_run(ladder, runs((top, 1), (top, 2), (below, 1))) == below
    assert profile.next_run(ladder, runs((top, 1), (top, 2), (below, 1), (below, 1))) == ladder[-3]
    assert profile.next_run(ladder, runs((top, 3))) == below              # overloaded, not a stall
    assert profile.next_run(ladder, runs(*[(ladder[-1 - k], 9) for k in range(6)])) is None    # six runs
    assert profile.next_run(ladder, runs((ladder[0], 5))) is None


def test_a_probe_fits_within_the_budget_with_at_most_one_late_frame():
    """A probe fits when its p99 is within the budget and at most one frame was late (a stall of the
    machine; the measured run decides); a second late frame, or a p99 over budget, does not fit."""
    budget = {"metric": "frame_ms_own.p99 (release to done, quota in effect, host stalls apart)", "ms": 13.3}
    probe = lambda p99, late: {"frame_ms": {"p99": p99}, "cpu_ms": {"p99": 1.0}, "deadline_misses": late}  # noqa: E731
    assert profile.probe_fits(probe(9.0, 0), budget) and profile.probe_fits(probe(9.0, 1), budget)
    assert not profile.probe_fits(probe(9.0, 2), budget)
    assert not profile.probe_fits(probe(14.0, 0), budget)
    modelled = {"metric": "cpu_ms.p99 against the quota share (modelled, quota not enforced)", "ms": 3.3}
    assert profile.probe_fits(probe(99.0, 0), modelled) and not profile.probe_fits({**probe(1.0, 0), "cpu_ms": {"p99": 4.0}}, modelled)


def test_late_frames_the_host_stalled_are_told_from_frames_over_their_own_budget():
    """At a 25 % quota (CFS period 10 ms) a 60 Hz frame that needs 1 ms of CPU is done within 1/0.25 + 7.5
    = 11.5 ms: late anyway, the host stalled it. One that needs 3.5 ms (21.5 ms at the quota) was late
    of its own. A skipped frame takes the cause of the frame before it; without an enforced quota the
    frame's CPU time alone is what it needs."""
    import numpy as np
    period = 1 / 60
    ms = lambda *x: np.array(x) / 1e3  # noqa: E731
    resp, cpu = ms(5, 70, 40, 20, 30, 12), ms(1, 1, np.nan, 3.5, np.nan, 3.5)
    stall, own = profile.host_stalls(resp, cpu, period, quota=0.25, enforced=True, cfs_period=0.01)
    assert stall.tolist() == [False, True, True, False, False, False]
    assert own.tolist() == [False, False, False, True, True, False]
    stall, own = profile.host_stalls(ms(40, 21, 10), ms(1, 20, 9), period, quota=0.25, enforced=False)
    assert stall.tolist() == [True, False, False] and own.tolist() == [False, True, False]


class ScriptedClock:
    """Wall and thread-CPU clocks that move only when told: a frame costs what the script says."""

    def __init__(self):
        self.wall = self.cpu = self.waited = 0.0

    def sleep(self, s):
        self.wall += s


def test_a_scripted_stall_is_reported_apart_and_costs_no_rung(monkeypatch):
    """A paced run on scripted clocks (1 ms of CPU a frame at 60 Hz, quota 0.25 enforced): a 70 ms stall
    of the host at frame 100 makes it and the frames it skipped late, all counted as host stalls with
    their wait to run, none as the frame's own; the probe still fits. A frame that really costs 15 ms
    of CPU is the frame's own miss, and the probe does not fit with two of them."""
    import numpy as np
    from firmware_bridge.links import Pacer
    from edge.pipeline import STAGES

    class Pipe:
        refiner, samples, timing, switch_count = None, 1, False, 0
        stage_ns = np.zeros(len(STAGES) + 1)

    class Service:
        pipeline, tick_marks = Pipe(), (0.0, 0.0, 0.0, 0.0)

        def close(self):
            pass

    monkeypatch.setattr(profile, "board_service", lambda *a: Service())
    cfg = {"hz": 60.0, "quota": 0.25, "enforced": True, "period_ms": 10.0, "refine_steps": 0}
    budget = {"metric": "frame_ms_own.p99 (release to done, quota in effect, host stalls apart)", "ms": 0.8e3 / 60}

    def scripted(costs):
        run = profile.PacedRun(cfg, 1, 300, False, None, 0)
        c = ScriptedClock()
        run.clock, run.cpu_clock, run.run_delay = (lambda: c.wall), (lambda: c.cpu), (lambda: c.waited)
        run.pacer = Pacer(60.0, run.clock, c.sleep)

        def tick(k):
            wall, cpu = costs.get(k - run.WARM, (0.004, 0.001))     # 1 ms of CPU: 4 ms at the quota
            c.wall, c.cpu, c.waited = c.wall + wall, c.cpu + cpu, c.waited + wall - cpu
        run.tick = tick
        run.warm_up()
        run.measure("scripted")
        return run.stats()

    st = scripted({100: (0.070, 0.001)})
    assert st["deadline_misses"] >= 4 and st["host_stalls"] == st["deadline_misses"] and st["own_misses"] == 0
    assert st["host"]["stalls_at"][0] == 100 and st["host"]["stalled_frames_wait_to_run_ms"]["max"] == pytest.approx(69.0)
    assert profile.probe_fits(st, budget)
    st = scripted({100: (0.020, 0.015), 200: (0.020, 0.015)})
    assert st["own_misses"] >= 2 and st["host_stalls"] == st["deadline_misses"] - st["own_misses"]
    assert not profile.probe_fits(st, budget)


def test_a_busy_neighbour_on_the_profiled_core_is_measured_and_warned_of(tmp_path, capsys):
    """Other tasks on the worker's core are measured (the core's busy time less the worker's own) and a
    share over 2 % is warned of: on a VM their memory traffic is charged to the frame's CPU time."""
    import subprocess
    import sys
    core = min(os.sched_getaffinity(0))
    spin = subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{core}}})\nwhile True: pass"])
    try:
        time.sleep(0.3)
        r = run(tmp_path, "--samples", "1", "--frames", "120", "--refine-steps", "0", "--no-cgroup")
    finally:
        spin.kill()
        spin.wait()
    near = r["core_neighbours"]
    assert near["core"] == core and r["pinned_core"] == [core]
    assert near["share"] > 0.2, near            # the spinner had about half the core
    assert "other tasks used" in capsys.readouterr().err
