"""Each `edge` subcommand run as a user runs it: a subprocess (`python -m edgecli`, what the `edge`
script calls) on the bundled sample and session, simulated devices on real ptys where a board would have
hardware, with short bounded runs. Checks the exit code, what the command prints and the files it says
it writes; the functions behind the commands have their own tests."""
import json
import os
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "cmu_09_12_walk.npz"
SESSION = ROOT / "samples" / "cmu_09_12_walk.session.npz"


def edge_cmd(*args):
    return [sys.executable, "-m", "edgecli", *map(str, args)]


def edge(*args, cwd, timeout=120, env=None):
    """`edge ARGS...` in `cwd`; the CompletedProcess (text stdout and stderr)."""
    return subprocess.run(edge_cmd(*args), cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **(env or {})})


def said(run):
    return f"exit {run.returncode}\nstdout:\n{run.stdout[-3000:]}\nstderr:\n{run.stderr[-3000:]}"


def needs_plotting():
    pytest.importorskip("matplotlib", reason="the report needs the [viz] extra (pip install -e '.[viz]')")


def test_eval_with_report_writes_the_metrics_and_the_report_page(tmp_path):
    """`edge eval --data CLIP --report OUT` in one go (it used to crash with UnboundLocalError on Path)."""
    needs_plotting()
    run = edge("eval", "--data", SAMPLE, "--max-frames", 150, "--samples", 2, "--no-ssi", "--json", "out/e.json",
               "--report", "out/report", cwd=tmp_path)
    assert run.returncode == 0, said(run)
    metrics = json.loads((tmp_path / "out/e.json").read_text())
    assert metrics["frames"] > 0 and 0 < metrics["mpjpe_cm"] < 50
    assert metrics["ssi"] is False and metrics["ssi_switches"] == 0
    assert (tmp_path / "out/report/index.html").is_file()
    assert list((tmp_path / "out/report/dump").glob("*.npz")), "the report's dump folder is empty"
    assert "wrote" in run.stdout and "index.html" in run.stdout


def test_replay_without_json_prints_its_summary_and_writes_nothing(tmp_path):
    run = edge("replay", SESSION, "--speed", "max", "--seconds", 2, "--samples", 4, cwd=tmp_path)
    assert run.returncode == 0, said(run)
    assert "frames_in=" in run.stderr and "mpjpe_cm=" in run.stderr and "latency p50" in run.stderr
    assert list(tmp_path.iterdir()) == [], "a replay without --json or --bvh wrote files"


def test_replay_with_a_report_and_no_json_keeps_the_json_in_the_report_folder(tmp_path):
    needs_plotting()
    run = edge("replay", SESSION, "--speed", "max", "--seconds", 2, "--samples", 2, "--report", "out/report",
               cwd=tmp_path)
    assert run.returncode == 0, said(run)
    assert json.loads((tmp_path / "out/report/replay.json").read_text())["frames_out"] > 60
    assert (tmp_path / "out/report/index.html").is_file()


class Lines:
    """A running process's stderr, read line by line on a thread, so a test can wait for a line."""

    def __init__(self, stream):
        self.lines, self._stream = [], stream
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self):
        for line in self._stream:
            self.lines.append(line)

    def wait_for(self, text, timeout, proc=None):
        """True once a line holds `text`; False after `timeout` s or once `proc` has exited without it."""
        give_up = time.monotonic() + timeout
        while time.monotonic() < give_up:
            done = proc is not None and proc.poll() is not None
            if done:
                self._thread.join(5)
            if any(text in line for line in self.lines):
                return True
            if done:
                return False
            time.sleep(0.02)
        return False

    def text(self):
        self._thread.join(5)
        return "".join(self.lines)


def play_headset(fd, stop, hz=60.0):
    """The bundled take's head and hands as a headset sends them (HEADSET_POSE frames) on a pty master."""
    from motion.takes import from_sample
    from firmware_bridge.samples import HeadsetSample
    from firmware_bridge.wire import messages
    sig = from_sample(SAMPLE).signals
    t0, k = time.monotonic(), 0
    while not stop.is_set():
        i = k % len(sig.head_pos)
        frame = HeadsetSample(time.monotonic(), sig.head_pos[i], sig.head_rot[i], sig.hand_pos[i], sig.hand_rot[i])
        os.write(fd, messages.encode_headset_pose(frame, k & 0xFFFF))
        k += 1
        time.sleep(max(0.0, t0 + k / hz - time.monotonic()))


def test_run_waits_for_a_headset_plugged_in_after_it_started_then_streams_poses(tmp_path):
    """`edge run --config --seconds --json` on a board whose headset port is not there at start (the
    normal case under systemd): the service waits and says so, the port appears (a pty behind the path,
    as udev makes a symlink), headset frames arrive and poses come back on the same link."""
    from edgetools.listen import Listener
    from edgetools.sim.devices import close_pty_at, open_pty_at
    port = tmp_path / "ttyHEADSET"
    (tmp_path / "board.toml").write_text(f'[headset]\nurl = "serial://{port}?role=headset"\n\n'
                                         '[runtime]\nsamples = 2\nlookahead = 2\nadaptive = false\n')
    proc = subprocess.Popen(edge_cmd("run", "--config", "board.toml", "--seconds", 6, "--json", "out/run.json"),
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    err = Lines(proc.stderr)
    stop, master = threading.Event(), None
    try:
        assert err.wait_for(f"headset: waiting for {port}", timeout=30, proc=proc), err.text()
        assert proc.poll() is None, "the service exited instead of waiting for the headset"
        master, slave = open_pty_at(port)
        tty.setraw(slave)            # a UART echoes nothing; a fresh pty would, until the service opens it
        player = threading.Thread(target=play_headset, args=(master, stop), daemon=True)
        player.start()
        ear, poses = Listener(fd=master), []
        while proc.poll() is None:
            poses += ear.poll(0.05)
        stop.set()
        player.join(2)
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
        if master is not None:
            close_pty_at(port, master, slave)
    text = err.text()
    assert proc.returncode == 0, text
    summary = json.loads((tmp_path / "out/run.json").read_text())
    assert summary["no_input"] > 0, "the pipeline ticked before the headset was there"
    assert summary["frames_out"] > 60 and len(poses) > 60, (summary, len(poses), text)
    assert ear.stats["corrupt"] == 0


def raw_pty():
    """A pty whose slave end a command opens by path, in raw mode as a UART is (no echo):
    (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


def play_headset_and_hub(headset_fd, hub_fd, stop, hz=60.0):
    """The bundled take as a headset (HEADSET_POSE) and a tracker hub with the waist puck
    (TRACKER_SAMPLES) send it, each on its pty master."""
    from tests.test_service import feed
    from motion.takes import from_sample
    feed(from_sample(SAMPLE), headset_fd, hub_fd, stop, hz)


class Devices:
    """A simulated headset and tracker hub on raw ptys, playing the bundled take while the block runs."""

    def __enter__(self):
        self.headset, self.hub = raw_pty(), raw_pty()
        self.stop = threading.Event()
        self.player = threading.Thread(target=play_headset_and_hub, args=(self.headset[0], self.hub[0], self.stop),
                                       daemon=True)
        self.player.start()
        return self

    def config(self, folder):
        path = Path(folder) / "board.toml"
        path.write_text(f'[headset]\nurl = "serial://{self.headset[2]}?role=headset"\n\n'
                        f'[[trackers]]\nurl = "serial://{self.hub[2]}?role=hub&trackers=0:waist"\n')
        return path

    def __exit__(self, *exc):
        self.stop.set()
        self.player.join(2)
        for fd in (*self.headset[:2], *self.hub[:2]):
            os.close(fd)


def test_report_draws_the_chosen_clip_of_an_eval_run_with_the_main_eval_flags(tmp_path):
    """`edge eval --data --samples --max-frames --trackers --faults --precision --json --dump`, then `edge
    report RUN.json --dump --out --clip` (with the short picture flags) on what it wrote."""
    needs_plotting()
    run = edge("eval", "--data", SAMPLE, "--samples", 4, "--max-frames", 150, "--trackers", "l_shin,r_shin",
               "--faults", "disconnect", "--precision", "fp32", "--json", "out/e.json", "--dump", "out/dump",
               cwd=tmp_path)
    assert run.returncode == 0, said(run)
    metrics = json.loads((tmp_path / "out/e.json").read_text())
    assert metrics["samples"] == 4 and metrics["precision"] == "fp32" and metrics["faults"] == "disconnect", metrics
    assert metrics["trackers"] == ["waist", "l_shin", "r_shin"], metrics["trackers"]
    dumps = sorted((tmp_path / "out/dump").glob("*.npz"))
    assert len(dumps) == 1
    run = edge("report", "out/e.json", "--dump", "out/dump", "--out", "out/report", "--clip", dumps[0].name,
               "--every", 10, "--strip-frames", 3, "--gif-seconds", 1, cwd=tmp_path)
    assert run.returncode == 0, said(run)
    page = (tmp_path / "out/report/index.html").read_text()
    images = [p.name for p in (tmp_path / "out/report").iterdir() if p.suffix in (".png", ".gif")]
    assert any(name.endswith(".gif") for name in images) and len(images) >= 3, images
    assert all(name in page for name in images)
    assert edge("report", "out/e.json", "--dump", "out/dump", "--out", "out/r2", "--clip", "nope.npz",
                cwd=tmp_path).returncode != 0, "an unknown --clip was accepted"


def test_ssi_study_writes_the_rate_for_each_n(tmp_path):
    """`edge ssi-study --data --task --samples --runs --max-clips --json` on the bundled take (it has no
    kick, so the collision-avoidance task; the kick tasks say so and exit non-zero)."""
    run = edge("ssi-study", "--data", SAMPLE, "--task", "avoid", "--samples", "1,4", "--runs", 1, "--max-clips", 1,
               "--json", "out/study.json", cwd=tmp_path)
    assert run.returncode == 0, said(run)
    study = json.loads((tmp_path / "out/study.json").read_text())
    assert study["task"] == "avoid" and [r["samples"] for r in study["results"]] == [1, 4]
    kick = edge("ssi-study", "--data", SAMPLE, "--task", "high-kick", "--samples", "1", "--runs", 1,
                "--json", "out/kick.json", cwd=tmp_path)
    assert kick.returncode != 0 and "has a high-kick event" in kick.stderr, said(kick)


def test_replay_main_flags_write_the_json_bvh_and_report(tmp_path):
    """`edge replay TAKE --transport --trackers --faults --speed max --samples --precision --seconds --json
    --bvh --report`: a sample take (with ground truth) through every transport, two shin IMUs, packet loss."""
    needs_plotting()
    run = edge("replay", SAMPLE, "--transport", "serial,i2c,can", "--trackers", "l_shin,r_shin", "--faults", "loss",
               "--speed", "max", "--samples", 4, "--precision", "fp32", "--seconds", 2, "--json", "out/r.json",
               "--bvh", "out/r.bvh", "--report", "out/report", cwd=tmp_path)
    assert run.returncode == 0, said(run)
    result = json.loads((tmp_path / "out/r.json").read_text())
    assert result["frames_out"] > 60 and result["poses_decoded"] > 60 and result["mpjpe_cm"] < 50, result
    assert result["packets_lost"] > 0, "--faults loss lost nothing"
    assert "MOTION" in (tmp_path / "out/r.bvh").read_text()
    assert (tmp_path / "out/report/index.html").is_file()
    assert "wrote out/r.json and out/r.bvh" in run.stderr


def test_calibrate_stores_the_body_size_and_tracker_mounting(tmp_path):
    """`edge calibrate --config --seconds --out` with a headset and a waist puck on a tracker hub (ptys);
    `edge replay --calibration` reads the file it wrote."""
    with Devices() as devices:
        run = edge("calibrate", "--config", devices.config(tmp_path), "--seconds", 1, "--out", "cal.json",
                   cwd=tmp_path, timeout=60)
    assert run.returncode == 0, said(run)
    cal = json.loads((tmp_path / "cal.json").read_text())
    assert "waist" in json.dumps(cal) and "height scale" in run.stderr, cal
    # the session walks, arms down: the body's height is measured, the arms are said not to be
    assert "a body about" in run.stderr and "arms not measured (the arms were not straight out" in run.stderr, said(run)
    replay = edge("replay", SESSION, "--speed", "max", "--seconds", 1, "--samples", 1, "--calibration", "cal.json",
                  cwd=tmp_path)
    assert replay.returncode == 0, said(replay)


def test_calibrate_with_legs_asks_for_the_hand_at_the_hip_and_says_why_it_could_not_measure(tmp_path):
    """`edge calibrate --legs`: after the T-pose, the left controller at the hip; the session walks, so the
    hold is refused with what to do, the file is still written, and the legs are said not measured."""
    with Devices() as devices:
        run = edge("calibrate", "--config", devices.config(tmp_path), "--seconds", 1, "--out", "cal.json", "--legs",
                   cwd=tmp_path, timeout=60)
    assert run.returncode == 0, said(run)
    assert "bony point at the side of your left hip" in run.stderr, said(run)
    assert "legs not measured (the left controller" in run.stderr, said(run)
    assert json.loads((tmp_path / "cal.json").read_text())["leg_length_m"] is None


def test_calibrate_without_its_devices_names_the_missing_one(tmp_path):
    (tmp_path / "board.toml").write_text(f'[headset]\nurl = "serial://{tmp_path}/ttyNONE?role=headset"\n')
    run = edge("calibrate", "--config", "board.toml", "--seconds", 1, "--out", "cal.json", cwd=tmp_path)
    assert run.returncode == 2 and "ttyNONE" in run.stderr and "plugged in" in run.stderr, said(run)
    assert not (tmp_path / "cal.json").exists()


def test_record_captures_a_session_that_replay_plays_back(tmp_path):
    """`edge record --config --seconds --out` on a headset and a tracker hub (ptys), then `edge replay` of
    the file it wrote."""
    with Devices() as devices:
        run = edge("record", "--config", devices.config(tmp_path), "--seconds", 1.5, "--out", "take.npz",
                   cwd=tmp_path, timeout=60)
    assert run.returncode == 0, said(run)
    assert (tmp_path / "take.npz").is_file() and "headset frames" in run.stderr
    from edgetools.sim.session import Session
    session = Session.load(tmp_path / "take.npz")
    assert len(session.headset.frames) > 45 and len(session.hub.frames) > 45, run.stderr
    replay = edge("replay", "take.npz", "--speed", "max", "--samples", 2, "--json", "r.json", cwd=tmp_path)
    assert replay.returncode == 0, said(replay)
    assert json.loads((tmp_path / "r.json").read_text())["frames_out"] > 30


class PoseBoard:
    """A simulated board writing POSE_FRAMEs at 60 Hz on a raw pty while the block runs; `path` is the
    port a host program opens."""

    def __enter__(self):
        self.master, self.slave, self.path = raw_pty()
        self.stop = threading.Event()
        self.writer = threading.Thread(target=self._write, daemon=True)
        self.writer.start()
        return self

    def _write(self):
        import numpy as np
        from firmware_bridge.wire import messages
        k = 0
        while not self.stop.is_set():
            frame = messages.PoseFrame(time.monotonic(), np.array([0, 0.95, 0]), np.tile([1.0, 0, 0, 0], (21, 1)))
            os.write(self.master, messages.encode_pose_frame(frame, k & 0xFFFF))
            k += 1
            time.sleep(1 / 60)

    def __exit__(self, *exc):
        self.stop.set()
        self.writer.join(2)
        os.close(self.master)
        os.close(self.slave)


def recorded_frames(path):
    from firmware_bridge.wire import messages
    return messages.FrameReader(accept=(messages.POSE_FRAME,)).feed(Path(path).read_bytes())


def test_listen_decodes_the_pose_stream_and_records_its_bytes(tmp_path):
    """`edge listen PORT --baud --seconds --record` on a pty a simulated board writes pose frames to."""
    with PoseBoard() as board:
        run = edge("listen", board.path, "--baud", 460800, "--seconds", 1.5, "--record", "pose.bin", cwd=tmp_path,
                   timeout=60)
    assert run.returncode == 0, said(run)
    assert "edge listen |" in run.stderr, said(run)
    frames = int(run.stderr.rsplit("frames ", 1)[1].split()[0])
    corrupt = int(run.stderr.rsplit("corrupt ", 1)[1].split()[0])
    assert corrupt <= 1, said(run)        # at most the frame the port was opened in the middle of
    assert frames > 45, said(run)
    assert len(recorded_frames(tmp_path / "pose.bin")) >= frames - 1


def test_listen_plot_without_a_display_keeps_the_status_line_and_the_recording(tmp_path):
    """`edge listen PORT --plot --record` where there is no display: it says so, shows the status line
    instead, and still records (the flags are the same with and without --plot)."""
    needs_plotting()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
    with PoseBoard() as board:
        run = subprocess.run(edge_cmd("listen", board.path, "--plot", "--seconds", 1.5, "--record", "pose.bin"),
                             cwd=tmp_path, capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode == 0, said(run)
    assert "display" in run.stderr and "edge listen |" in run.stderr, said(run)
    assert len(recorded_frames(tmp_path / "pose.bin")) > 45
    missing = subprocess.run(edge_cmd("listen", tmp_path / "ttyNONE", "--plot", "--seconds", 1), cwd=tmp_path,
                             capture_output=True, text=True, timeout=60, env=env)
    assert missing.returncode == 2 and "ttyNONE" in missing.stderr and "Traceback" not in missing.stderr, said(missing)


def test_listen_on_a_port_that_is_not_there_says_so(tmp_path):
    run = edge("listen", tmp_path / "ttyNONE", "--seconds", 1, cwd=tmp_path)
    assert run.returncode == 2 and "ttyNONE" in run.stderr, said(run)


def test_profile_at_a_fixed_n_writes_the_profile(tmp_path):
    """`edge profile --samples --frames --hz --precision --no-cgroup --json` (the quota and the auto search
    have their own tests in test_profile.py; --quick is about 40 s)."""
    run = edge("profile", "--samples", 2, "--frames", 60, "--hz", 60, "--precision", "int8", "--no-cgroup",
               "--json", "out/p.json", cwd=tmp_path)
    assert run.returncode == 0, said(run)
    profile = json.loads((tmp_path / "out/p.json").read_text())
    assert profile["chosen_samples"] == 2 and profile["frames"] == 60 and profile["frame_ms"]["p50"] > 0


def test_every_subcommand_in_edge_help_has_a_subprocess_test_here(tmp_path):
    run = edge("--help", cwd=tmp_path)
    assert run.returncode == 0, said(run)
    listed = run.stdout.split("{", 1)[1].split("}", 1)[0].split(",")
    assert {"eval", "replay", "run", "calibrate", "listen", "record", "report", "profile", "ssi-study"} <= set(listed)
    tests = [name for name in globals() if name.startswith("test_")]
    untested = [cmd for cmd in listed if not any(name.startswith(f"test_{cmd.replace('-', '_')}_") for name in tests)]
    assert not untested, f"no subprocess test in tests/test_cli.py for: edge {', edge '.join(untested)}"


def test_soak_refuses_what_it_cannot_run_and_says_how(tmp_path):
    """`edge soak` with parts too short or a clip that is not there stops before it starts, saying what to
    change (tests/test_soak.py runs a real minute of it)."""
    run = edge("soak", "--minutes", 1, "--part-s", 3, "--json", "s.json", cwd=tmp_path)
    assert run.returncode == 2 and "--part-s >= 5" in run.stderr, said(run)
    run = edge("soak", "--minutes", 1, "--source", "nowhere.bvh", "--json", "s.json", cwd=tmp_path)
    assert run.returncode == 2 and "nowhere.bvh: no such file" in run.stderr, said(run)
    assert not (tmp_path / "s.json").exists()


def test_replay_help_names_every_fault_profile(tmp_path):
    from edgetools.sim.session import FAULTS
    run = edge("replay", "--help", cwd=tmp_path, env={"COLUMNS": "1000"})
    assert run.returncode == 0, said(run)
    line = next(ln for ln in run.stdout.splitlines() if "--faults" in ln and "profile" in ln)
    missing = [name for name in FAULTS if name not in line]
    assert not missing, f"edge replay --help does not name the fault profiles {missing}"
