"""Hardware-in-the-loop: sessions replayed through simulated devices into the real board service."""
import threading
import time

import numpy as np
import pytest

from motion.takes import from_sample
from edgetools.sim.record import CanTap, SerialTap
from edgetools.sim.devices import CanDevice, SerialDevice, SimClock
from edgetools.sim.replay import replay
from edgetools.sim.session import FAULTS, Session, fault_profile, synthesize
from tests.conftest import SAMPLE

SECONDS = 4.0
LOOKAHEAD = 10


@pytest.fixture(scope="module")
def take():
    return from_sample(SAMPLE)


def run(take, transports=("serial", "i2c", "can"), faults="clean", seconds=SECONDS, seed=0):
    f = fault_profile(faults)
    return replay(synthesize(take, transports, f, seed), "max", seconds=seconds, faults=f, runtime={"samples": 8, "lookahead": LOOKAHEAD})


@pytest.fixture(scope="module")
def clean(take):
    return run(take)


@pytest.mark.parametrize("transports", [("serial",), ("i2c",), ("can",), ("serial", "i2c", "can")])
def test_every_frame_reaches_the_host_over_each_transport(take, transports):
    r = run(take, transports)
    assert r["errors"] == []
    # The first tick can come before the pty has delivered the first headset frame.
    assert r["frames_in"] >= int(SECONDS * 60) - 2 and r["frames_out"] == r["frames_in"] - LOOKAHEAD
    assert r["poses_decoded"] == r["frames_out"] and r["missing_output_frames"] == 0
    assert r["packets_corrupt"] == 0 and r["tracker_lost_events"] == 0
    assert r["mpjpe_cm"] < 8.0
    opened = " ".join(r["transports"]["opened"])
    assert "serial://" in opened and ("sim://i2c/" in opened) == ("i2c" in transports) and ("can://" in opened) == ("can" in transports)


@pytest.mark.parametrize("profile", sorted(FAULTS))
def test_every_fault_profile_keeps_the_output_going(take, clean, profile):
    r = run(take, faults=profile)
    assert r["errors"] == [], r["errors"]
    assert r["frames_out"] == r["frames_in"] - LOOKAHEAD
    assert r["poses_decoded"] > 0.8 * r["frames_out"]
    if profile == "corrupt":
        assert r["packets_corrupt"] > 0
    if profile in ("loss",):
        assert r["packets_lost"] > 0
    if profile in ("disconnect", "can-busoff", "hand-loss"):
        assert r["tracker_lost_events"] > 0
    if profile in ("hand-loss", "clock-jump", "i2c-errors", "noise"):
        assert r["missing_output_frames"] == 0 and r["poses_decoded"] == r["frames_out"]
    if profile == "i2c-errors":           # the injected bus errors happened, were counted and retried
        assert r["device_errors"] > 0 and r["device_errors"] > clean["device_errors"]
    if profile == "clock-jump":           # a device clock went backwards and the board saw it
        assert r["clock_jumps"] > 0 and clean["clock_jumps"] == 0
    if profile == "unplug":
        assert r["reopens"] >= 1 and r["resume_after_replug_s"] is not None and r["resume_after_replug_s"] < 1.0
    if profile != "unplug":       # with the headset gone for 0.5 s the body is held, so errors are large then
        assert r["mpjpe_cm"] < 3 * clean["mpjpe_cm"]


def test_faults_can_be_given_as_json_and_bad_ones_are_named():
    assert fault_profile('{"ber": 0.001}') == {"ber": 0.001}
    with pytest.raises(ValueError, match="unknown fault profile 'wobble'"):
        fault_profile("wobble")
    with pytest.raises(ValueError, match="unknown fault parameter"):
        fault_profile('{"shake": 1}')


def test_session_files_round_trip(take, tmp_path):
    s = synthesize(take, seconds=2.0)
    s.save(tmp_path / "s.npz")
    back = Session.load(tmp_path / "s.npz")
    assert back.digest() == s.digest() and np.allclose(back.gt_pos, s.gt_pos, atol=1e-6)
    assert (tmp_path / "s.npz").stat().st_size < 1_000_000


def test_recording_a_replay_reproduces_its_bytes_exactly(take, tmp_path):
    s = synthesize(take, ("serial", "can"), seconds=1.5)
    clock = SimClock(realtime=True)
    dev = SerialDevice("headset", s.headset, tmp_path)
    hub = SerialDevice("hub", s.hub, tmp_path)
    can_dev = CanDevice(s, "edgepose-record-test", clock)
    taps = [SerialTap(dev.path, 460800, clock), SerialTap(hub.path, 460800, clock),
            CanTap("virtual", "edgepose-record-test", clock)]
    t0 = time.monotonic()
    while time.monotonic() - t0 < s.duration + 0.3:
        now = time.monotonic() - t0
        for d in (dev, hub, can_dev):
            d.emit_until(now)
        for tap in taps:
            tap.poll()
        time.sleep(0.002)
    for tap in taps:
        tap.poll()
    sent = b"".join(s.headset.frames), b"".join(s.hub.frames), np.asarray(s.can_data).tobytes()
    got = b"".join(taps[0].log.frames), b"".join(taps[1].log.frames), np.array(taps[2].data, np.uint8).tobytes()
    import hashlib
    assert [hashlib.sha256(x).hexdigest() for x in got] == [hashlib.sha256(x).hexdigest() for x in sent]
    assert list(taps[2].ids) == list(s.can_id)
    for x in taps + [dev, hub, can_dev]:
        x.close()


def test_a_realtime_replay_that_first_builds_the_compiled_core_still_tracks(tmp_path):
    """The first run on a machine compiles edge/native (seconds of cc). Done after the replay's clock had
    started, the service began seconds behind its own devices and scored ~48 cm for the whole take."""
    import json
    import os
    import subprocess
    import sys
    out = tmp_path / "r.json"
    env = {**os.environ, "EDGEPOSE_CACHE": str(tmp_path / "cache")}       # an empty cache: build on first use
    code = ("import sys; from edgecli import main; "
            f"sys.exit(main(['replay', {str(SAMPLE).replace('.npz', '.session.npz')!r}, '--seconds', '3', "
            f"'--json', {str(out)!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "cache" / "native").exists()
    assert json.loads(out.read_text())["mpjpe_cm"] < 12.0


def test_extra_trackers_ride_the_simulated_hub_and_can_and_feed_the_model(take):
    """--trackers: the shins go on the serial hub, the feet on CAN, and the model reads all four."""
    from edge.options import PipelineOptions
    from edge.pipeline import Pipeline
    session = synthesize(take, ("serial", "i2c", "can"), {}, 0, trackers=("l_shin", "r_shin", "l_foot", "r_foot"))
    assert session.meta["placement"] == {"i2c": ["waist"], "hub": ["l_shin", "r_shin"], "can": ["l_foot", "r_foot"],
                                         "slimevr": []}
    result = replay(session, "max", seconds=SECONDS, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    assert set(result["trackers"]) == {"waist", "l_shin", "r_shin", "l_foot", "r_foot"}
    assert result["errors"] == [] and result["poses_decoded"] > 0
    if Pipeline(PipelineOptions(samples=1)).imus:
        assert result["trackers_used_by_model"] == ["l_shin", "r_shin", "l_foot", "r_foot"]
        bare = replay(synthesize(take, ("serial", "i2c", "can"), {}, 0, trackers=()), "max", seconds=SECONDS, runtime={"samples": 8, "lookahead": LOOKAHEAD})
        assert result["mpjpe_cm"] < bare["mpjpe_cm"]
    with pytest.raises(ValueError, match="need the serial hub or CAN"):
        synthesize(take, ("i2c",), {}, 0, trackers=("l_shin",))


def test_unplugging_a_foot_tracker_mid_replay_changes_the_pose_without_a_pop(take):
    """unplug-foot: the left foot's CAN tracker goes silent for good at 4 s; the replay reports the
    largest joint move per frame in the second before and after, and the fade keeps them alike."""
    f = fault_profile("unplug-foot")
    result = replay(synthesize(take, ("serial", "i2c", "can"), f, 0), "max", seconds=7.0, faults=f, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    u = result["tracker_unplug"]
    assert u["tracker"] == "l_foot" and result["tracker_lost_events"] >= 1
    assert u["largest_step_before_m"] > 0 and u["ratio"] < 1.5


def test_a_tracker_down_while_the_service_starts_is_ridden_through_and_reported(take):
    """The waist puck does not answer for the first two seconds, in real time (the BNO055's set-up
    falls inside the outage): the service starts without it, retries, reports it, and streams.
    (Each retry's set-up still runs on the tick thread and stalls it for its boot wait: the reader
    threads of the never-silent issue take device I/O off the tick.)"""
    session = synthesize(take, ("serial", "i2c", "can"), {}, 0)
    session.i2c_quat[:200] = np.nan                 # the puck NACKs for the first 2 s
    result = replay(session, "realtime", seconds=3.0, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    assert result["errors"] == [] and result["poses_decoded"] > 50
    assert any(url.startswith("sim://i2c/") for url in result["devices_down_at_start"])
    assert result["reopens"] >= 1


def test_the_documented_disconnect_replay_runs_to_the_end_in_real_time(tmp_path):
    """README's `edge replay samples/cmu_09_12_walk.npz --faults disconnect`, as a user runs it."""
    from edgecli import main as edge_main
    out = tmp_path / "r.json"
    assert edge_main(["replay", str(SAMPLE), "--faults", "disconnect", "--json", str(out)]) == 0
    import json
    r = json.loads(out.read_text())
    assert r["errors"] == [] and r["poses_decoded"] > 900 and r["tracker_lost_events"] > 0


def test_slimevr_trackers_replay_over_loopback_udp_and_a_restarted_one_is_back_at_once(take):
    """--transport slimevr: the waist and both shins are simulated SlimeVR trackers on loopback UDP;
    the right shin goes silent at 4 s for 2 s and then handshakes again."""
    f = fault_profile("slimevr-restart")
    session = synthesize(take, ("slimevr",), f, 0, trackers=("l_shin", "r_shin"))
    assert sorted(session.meta["slimevr_trackers"].values()) == ["l_shin", "r_shin", "waist"]
    result = replay(session, "max", seconds=8.0, faults=f, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    assert result["errors"] == [] and result["poses_decoded"] > 400
    assert set(result["trackers"]) == {"waist", "l_shin", "r_shin"}
    assert all(t["in_use"] and t["packets_per_s"] > 50 for t in result["slimevr"].values())
    back = result["slimevr_restart"]
    assert back["tracker"] == "r_shin" and back["in_use_again_after_s"] is not None
    assert back["in_use_again_after_s"] < 1.0


def test_a_garbage_flood_at_the_slimevr_port_is_counted_and_the_board_keeps_streaming(take):
    f = fault_profile("slimevr-flood")
    session = synthesize(take, ("slimevr",), f, 0, trackers=("l_shin", "r_shin"))
    result = replay(session, "realtime", seconds=2.5, faults=f, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    assert result["errors"] == [] and result["poses_decoded"] > 100
    assert result["packets_corrupt"] > 1000                     # counted and dropped, every one
    assert all(t["in_use"] for t in result["slimevr"].values())


def test_faults_a_recording_cannot_carry_name_the_profile_and_the_take_to_replay_instead(capsys):
    from edgetools.sim.sources import load_source
    rec = str(SAMPLE).replace(".npz", ".session.npz")
    load_source(rec, ("serial", "i2c", "can"), fault_profile("disconnect"))
    err = capsys.readouterr().err
    assert "fault profile(s) disconnect" in err and "replay " + str(SAMPLE) in err


def test_a_replay_whose_service_raised_exits_non_zero(tmp_path, monkeypatch, capsys):
    from edgecli import main as edge_main
    from firmware_bridge.service import Service
    real, calls = Service.step, []

    def flaky(self, now, due=None):
        calls.append(now)
        if len(calls) == 10:
            raise RuntimeError("a broken tick")
        return real(self, now, due)
    monkeypatch.setattr(Service, "step", flaky)
    code = edge_main(["replay", str(SAMPLE), "--speed", "max", "--seconds", "1", "--json", str(tmp_path / "r.json")])
    assert code == 1 and "a broken tick" in capsys.readouterr().err


def test_listener_raises_and_only_the_command_exits():
    from edgetools.listen import Listener
    with pytest.raises(OSError, match="cannot open /dev/ttyNOPE"):
        Listener("/dev/ttyNOPE")


def test_a_read_that_blocks_50_ms_every_200_ms_never_holds_the_tick():
    """slow-i2c: the waist BNO055's block read stalls for 50 ms of real time every 200 ms. With a reader
    thread per source (the board's way) the tick thread never waits in a read (no poll takes a frame
    period); with the tick thread reading the sources itself, the same replay's polls wait out the
    stalls and its ticks miss their deadlines (real time, real sleeps). What is counted is what the
    code controls, the tick thread's time in its polls, not the deadlines a busy machine can miss on
    its own. The full check, 3,600 ticks at N=32: `edge replay samples/cmu_09_12_walk.npz --faults
    slow-i2c --samples 32 --seconds 60 --json out/slow_i2c.json`."""
    from edgetools.sim.session import fault_profile
    f = fault_profile("slow-i2c")
    take = from_sample(SAMPLE)
    threaded = replay(synthesize(take, ("serial", "i2c", "can"), f, 0), "realtime", seconds=4.0, faults=f, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    inline = replay(synthesize(take, ("serial", "i2c", "can"), f, 0), "realtime", seconds=4.0, faults=f, threaded=False, runtime={"samples": 8, "lookahead": LOOKAHEAD})
    assert threaded["reader_threads"] >= 3 and inline["reader_threads"] == 0
    # about 20 stalls in 4 s; a poll that only takes from queues is preempted for a frame hardly ever
    assert threaded["polls_held"] <= 1, threaded["polls_held"]
    assert inline["polls_held"] >= 10, inline["polls_held"]
    assert inline["deadline_misses"] >= 10          # about one in twelve ticks waits 50 ms for the chip


def test_a_replay_drives_vmc_and_vrchat_receivers_with_the_calibrated_body(tmp_path):
    """edge replay --vmc --vrchat to loopback receivers, decoded with python-osc against the published
    layouts: every VMC frame complete (Root, the 21 bones, OK, T), every VRChat message in the configured
    tracker set (and the head); with a 1.60 m user's calibration the head arrives where the headset is,
    within 2 cm (unscaled it would be 9 % higher)."""
    import socket
    from pythonosc.osc_packet import OscPacket
    from edge.calibration import Calibration
    from edge import quat as q
    from edge.signals import EYE_OFFSET
    from edge.skeleton import JOINT_NAMES, PARENTS
    from firmware_bridge.outputs.vmc import BONE_NAMES
    socks = {}
    for name in ("vmc", "vrchat"):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 23)
        s.bind(("127.0.0.1", 0))
        s.settimeout(0.2)
        socks[name] = s
    got = {name: [] for name in socks}
    stop = threading.Event()

    def listen(name):
        while not stop.is_set():
            try:
                got[name].append(socks[name].recv(65536))
            except socket.timeout:
                pass
    threads = [threading.Thread(target=listen, args=(n,), daemon=True) for n in socks]
    for t in threads:
        t.start()
    cal = tmp_path / "calibration.json"
    Calibration(height_scale=1.75 / 1.60).save(cal)
    trackers = ["pelvis", "l_ankle", "r_ankle"]
    session = synthesize(from_sample(SAMPLE), ("serial", "i2c", "can"), {}, 0)
    output = {"vmc": f"127.0.0.1:{socks['vmc'].getsockname()[1]}",
              "vrchat": f"127.0.0.1:{socks['vrchat'].getsockname()[1]}", "vrchat_trackers": trackers}
    r = replay(session, "max", seconds=4.0, runtime={"samples": 8, "lookahead": LOOKAHEAD, "calibration": str(cal)},
               output=output)
    time.sleep(0.3)
    stop.set()
    for t in threads:
        t.join()
    assert r["errors"] == [] and r["frames_out"] > 200
    # VMC: each frame's messages across its (split) bundles, in order.
    msgs = [(m.message.address, m.message.params) for d in got["vmc"] for m in OscPacket(d).messages]
    frames, cur = [], []
    for address, params in msgs:
        cur.append((address, params))
        if address == "/VMC/Ext/T":
            frames.append(cur)
            cur = []
    assert len(frames) == r["frames_out"] and max(len(d) for d in got["vmc"]) <= 1472
    k = 1.60 / 1.75
    eyes_vmc = []
    for f in frames:
        assert [a for a, _ in f] == ["/VMC/Ext/Root/Pos"] + ["/VMC/Ext/Bone/Pos"] * 21 + ["/VMC/Ext/OK", "/VMC/Ext/T"]
        bones = {p[0]: np.array(p[1:], float) for a, p in f if a == "/VMC/Ext/Bone/Pos"}
        assert list(bones) == list(BONE_NAMES)
        world_r, world_p = {}, {}       # FK in Unity's frame (x mirrored), quaternions x y z w
        for j in range(len(JOINT_NAMES)):
            local = bones[BONE_NAMES[j]]
            rot = np.array([local[6], *local[3:6]])
            if PARENTS[j] < 0:
                world_r[j], world_p[j] = rot, local[:3]
            else:
                pr = world_r[PARENTS[j]]
                world_r[j], world_p[j] = q.mul(pr, rot), world_p[PARENTS[j]] + q.rotate(pr, local[:3])
        head = JOINT_NAMES.index("head")
        eyes_vmc.append(world_p[head] + q.rotate(world_r[head], EYE_OFFSET * [-1, 1, 1] * k))
    # VRChat: only the configured trackers and the head, position and rotation each.
    vr = [(m.message.address, m.message.params) for d in got["vrchat"] for m in OscPacket(d).messages]
    allowed = {f"/tracking/trackers/{i}/{w}" for i in [*map(str, range(1, len(trackers) + 1)), "head"]
               for w in ("position", "rotation")}
    assert {a for a, _ in vr} == allowed and len(vr) == len(allowed) * r["frames_out"]
    head_vr = np.array([p for a, p in vr if a == "/tracking/trackers/head/position"])
    # Where the headset was: the session's own headset heights over the same span.
    headset = from_sample(SAMPLE).signals.head_pos[:240, 1]       # the headset's height the replay sent
    assert abs(np.median(head_vr[:, 1]) - np.median(np.array(eyes_vmc)[:, 1])) < 0.02     # VMC and VRChat agree
    assert abs(np.median(head_vr[:, 1]) - np.median(headset)) < 0.02, (np.median(head_vr[:, 1]), np.median(headset))
    for s in socks.values():
        s.close()


def test_edge_listen_reads_a_simulated_board_through_replays_pose_port(tmp_path):
    """`edge replay --pose-port PATH` puts the pose stream on a real pty; a Listener opened on PATH, as
    `edge listen PATH` opens it (pyserial), decodes it: edge listen without hardware."""
    from edgecli import main as edge_main
    from edgetools.listen import Listener
    port = tmp_path / "board"
    frames, done = [], threading.Event()

    def listen():
        while not port.exists() and not done.is_set():
            time.sleep(0.01)
        with Listener(str(port)) as ear:
            while not done.is_set():
                frames.extend(ear.poll(0.05))
    reader = threading.Thread(target=listen, daemon=True)
    reader.start()
    code = edge_main(["replay", str(SAMPLE), "--speed", "realtime", "--seconds", "2", "--pose-port", str(port),
                      "--json", str(tmp_path / "r.json")])
    done.set()
    reader.join(2.0)
    assert code == 0 and len(frames) > 60          # 2 s at 60 Hz, less the look-ahead and the start
    assert all(np.isfinite(f.rotations).all() for f in frames) and not port.exists()


def test_the_injected_faults_row_names_every_profile_that_was_injected():
    """The report's 'injected faults' row: timed faults where they happened, whole-take ones at 0 with
    how much (disconnect was missing from it)."""
    from edgetools.sim.replay_report import injected
    for name in sorted(FAULTS):
        if name == "clean":
            continue
        marks = injected(fault_profile(name))
        assert marks, f"{name} injects something the row does not show"
    assert injected(fault_profile("disconnect")) == [{"t": 0.0, "kind": "IMU drops 1 %/frame (DragPoser)"}]
    assert injected(fault_profile("unplug-foot"))[0] == {"t": 4.0, "kind": "unplug l_foot"}


def test_a_flaky_pair_of_foot_trackers_is_never_worse_than_none(take):
    """DragPoser's faulty-sensor protocol on two CAN foot IMUs (each frame one drops with 1 %, back
    after 100 frames) through the simulated devices, on the bundled take of a person the model never
    saw (CMU 09): the synchroniser's hold and fade and the training's outages keep the flaky feet at
    least as good as wearing none, and worse than steady ones."""
    def mpjpe(trackers, faults):
        f = fault_profile(faults)
        r = replay(synthesize(take, ("can",), f, 0, trackers=trackers), "max", faults=f,
                   runtime={"samples": 1, "lookahead": 0})
        assert r["errors"] == []
        return r["mpjpe_cm"]
    steady, none, flaky = mpjpe(("l_foot", "r_foot"), "clean"), mpjpe((), "clean"), mpjpe(("l_foot", "r_foot"), "disconnect")
    assert steady < flaky <= none, (steady, flaky, none)
