"""Each `edge` subcommand run as a user runs it: a subprocess (`python -m edgetools.cli`, what the `edge`
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
    return [sys.executable, "-m", "edgetools.cli", *map(str, args)]


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
    run = edge("eval", "--data", SAMPLE, "--max-frames", 150, "--json", "out/e.json", "--report", "out/report",
               cwd=tmp_path)
    assert run.returncode == 0, said(run)
    metrics = json.loads((tmp_path / "out/e.json").read_text())
    assert metrics["frames"] > 0 and 0 < metrics["mpjpe_cm"] < 50
    assert (tmp_path / "out/report/index.html").is_file()
    assert list((tmp_path / "out/report/dump").glob("*.npz")), "the report's dump folder is empty"
    assert "wrote" in run.stdout and "index.html" in run.stdout


def test_replay_without_json_prints_its_summary_and_writes_nothing(tmp_path):
    run = edge("replay", SESSION, "--speed", "max", "--seconds", 2, "--samples", 4, cwd=tmp_path)
    assert run.returncode == 0, said(run)
    assert "frames_in=" in run.stderr and "mpjpe_cm=" in run.stderr and "latency p50" in run.stderr
    assert list(tmp_path.iterdir()) == [], "a replay without --json or --bvh wrote files"


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
    from edgetools.takes import from_sample
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
