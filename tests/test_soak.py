"""edge soak (issue #55): one board for a long time on every transport, faults mixed in.

The minute CI runs is `edge soak --minutes 1` in real time with the checks a two-hour soak has, beside
the other test process: every check must hold but the harness keeping up (on a shared machine the
simulator may fall behind its own clock; the soak says so, and its late frames are then the harness's,
not the board's). The rest pins down the parts a soak is made of: traffic that runs on from part to
part as one device's would, and a verdict that fails on growth, on a late frame of the board's own
making and on a fault nobody counted.
"""
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from edgetools.sim.session import HUB_IDS, synthesize

ROOT = Path(__file__).resolve().parent.parent
WALK = ROOT / "samples" / "cmu_09_12_walk.npz"


def _frames(log):
    """A serial log's frames, decoded (each is one COBS frame with its delimiter)."""
    from firmware_bridge.wire.framing import decode_frame
    return [decode_frame(f[:-1]) for f in log.frames]


def test_a_part_made_after_another_runs_on_from_it_as_one_device_would():
    """A soak's part k+1 is the same devices going on: times after the last part's, the same device
    clocks (the headset's stamps keep their offset to true time), frame counters and SlimeVR packet
    numbers following on with no gap."""
    from edgetools.sim.soak import PLACE, TRACKERS, TRANSPORTS, _take
    take = _take(str(WALK))
    a = synthesize(take, TRANSPORTS, {}, seed=0, seconds=5.0, trackers=TRACKERS, place=PLACE)
    b = synthesize(take, TRANSPORTS, {}, seed=1, seconds=5.0, trackers=TRACKERS, place=PLACE, start=5.0,
                   clocks=a.meta["clocks"])
    assert max(a.headset.t) <= 5.0 <= min(b.headset.t) and b.i2c_t[0] >= 5.0 and b.can_t[0] >= 5.0
    ha, hb = _frames(a.headset), _frames(b.headset)
    assert (hb[0].seq - ha[-1].seq) % 65536 == 1
    offset = lambda frames, log: np.median([(f.t_us - round(t * 1e6)) % 2 ** 32 for f, t in zip(frames, log.t, strict=True)])
    assert abs(offset(hb, b.headset) - offset(ha, a.headset)) < 2000        # one clock (us; drift and jitter)
    ua, ub = _frames(a.hub), _frames(b.hub)
    assert (ub[0].seq - ua[-1].seq) % 65536 == 1
    from firmware_bridge.wire.slimevr import parse
    for mac in a.slimevr:
        na = [parse(f).number for f in a.slimevr[mac].frames]
        nb = [parse(f).number for f in b.slimevr[mac].frames]
        assert nb[0] == na[-1] + 1 and np.all(np.diff(na[1:] + nb) == 1)     # after the first part's SENSOR_INFO
    assert set(HUB_IDS.values()) >= set(PLACE["hub"])


def _soak_of(late=(), rss=(100.0,) * 13, errors=(), counted=True, minutes=12.0):
    """A Soak whose run is given: its samples a minute apart and its late ticks, for the verdict."""
    from edgetools.sim.soak import LATE_KINDS, Soak
    hz = 60.0
    ticks = int(minutes * 60 * hz)
    events = [{"fault": "corrupt bytes", "at_s": 20.0, "ends_s": 20.0, "counted": counted, "recovered_s": 0.2}]
    bench = SimpleNamespace(events=events, errors=list(errors), service=SimpleNamespace(stats={"frames_out": ticks}),
                            metrics=SimpleNamespace(decoded=ticks))
    soak = Soak(bench, minutes, 60.0, None, None)
    soak.hz, soak.ticks_run = hz, ticks
    soak.frame_ms = np.full(ticks + 1, 2.0)
    soak.late = np.zeros(ticks + 1, np.int8)
    for k, kind in late:
        soak.late[k] = 1 + LATE_KINDS.index(kind)
    n = len(rss)
    soak.samples = [{"t_min": m * minutes / (n - 1), "tick": int(m * ticks / (n - 1)), "rss_mb": r, "fds": 30,
                     "threads": 9, "frames_out": 100 * (m + 1), "host_poses": 100 * (m + 1),
                     "sources": {"serial": 100 * (m + 1)}, "late": {}} for m, r in enumerate(rss)]
    return soak


def test_the_verdict_passes_a_steady_run_and_fails_each_kind_of_trouble():
    good = _soak_of(late=[(500, "host"), (900, "fault")]).verdict()
    assert good["ok"], good["checks"]
    assert not _soak_of(late=[(700, "own")]).verdict()["checks"]["no_own_late_frames"]
    growing = _soak_of(rss=tuple(100.0 + 1.0 * m for m in range(13))).verdict()     # 60 MB an hour
    assert not growing["checks"]["rss_flat"] and growing["rss_growth_mb_per_h"] == pytest.approx(60.0, rel=0.01)
    assert not _soak_of(counted=False).verdict()["checks"]["every_fault_counted"]
    assert not _soak_of(errors=["tick 5: ValueError: x"]).verdict()["checks"]["no_tick_errors"]
    slow = _soak_of(minutes=21.0, rss=(100.0,) * 22)
    slow.frame_ms[36000:] = 3.0                          # the third ten minutes' tail 50 % longer
    assert not slow.verdict()["checks"]["p99_steady"]


def test_a_minute_on_every_transport_counts_and_recovers_from_each_fault(tmp_path):
    """`edge soak --minutes 1` as CI runs it (issue #55 item 4): the schedule's seven parts of 8 s, each
    with its fault, samples between them, and the two-hour soak's checks."""
    from edgetools.sim.soak import SCHEDULE
    out = tmp_path / "soak.json"
    try:
        import matplotlib  # noqa: F401
        plot = ("--plot", str(tmp_path / "soak.png"))
    except ImportError:
        plot = ()
    proc = subprocess.run([sys.executable, "-m", "edgecli", "soak", "--minutes", "1", "--part-s", "8",
                           "--sample-s", "8", "--json", str(out), *plot], cwd=ROOT, capture_output=True, text=True,
                          timeout=240)
    said = f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-3000:]}"
    assert proc.returncode in (0, 1), said
    s = json.loads(out.read_text())
    failed = {name for name, good in s["checks"].items() if not good}
    assert failed <= {"harness_kept_up"}, said
    assert s["ok"] == (proc.returncode == 0) == (not failed)
    for key in ("minutes", "rss_growth_mb_per_h", "fd_growth", "thread_growth", "own_late_frames",
                "faults_injected", "faults_recovered", "frames_out", "ok"):
        assert key in s, key
    assert s["minutes"] == pytest.approx(1.0, abs=0.01)
    assert {e["fault"] for e in s["faults"]} == {f.name for f in SCHEDULE if f.name != "none"}
    assert s["faults_recovered"] == s["faults_injected"] >= 6
    assert s["frames_out"] >= 0.98 * 3600 and s["host_poses"] >= 0.95 * 3600
    rows = [json.loads(x) for x in Path(s["lines"]).read_text().splitlines()]
    assert len(rows) == 7 and all(r["rss_mb"] > 0 and r["fds"] > 0 for r in rows)
    # the machine's load beside the board's: the soak's process is part of the machine's busy time
    assert all(0 < r["load"]["soak_process_cores"] <= r["load"]["machine_cores"] + 0.05 for r in rows), rows
    assert s["own_late_at"] == [{"t_min": r["t_min"], "own": r["late"]["own"], "load": r["load"]}
                                for r in rows if r["late"]["own"]]
    assert not plot or (tmp_path / "soak.png").stat().st_size > 10_000
