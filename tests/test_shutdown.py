"""Nothing lost on the way down (#55 item 3): SIGTERM (systemd) or Ctrl-C at any moment of `edge run`,
`edge record` or `edge calibrate` leaves files that load, and a calibration is the old file or the new
one, never part of one (edge.shutdown)."""
import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest

from edge.calibration import Calibration
from edge.shutdown import StopSignals, replace_whole
from motion import bvh
from tests.test_cli import Devices, edge_cmd


def started(folder):
    """`edge run` of the simulated devices into a BVH and a JSON summary, in `folder`."""
    return subprocess.Popen(edge_cmd("run", "--config", "board.toml", "--seconds", 60, "--json", "out/run.json"),
                            cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def sigterm_after(seconds, folder, *args):
    """`edge ARGS...` in `folder`, sent SIGTERM after `seconds`: (the finished process, its stderr)."""
    proc = subprocess.Popen(edge_cmd(*args), cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(seconds)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc, err


def wait_until(condition, timeout, proc):
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        if condition():
            return True
        time.sleep(0.01)
    return False


def test_sigterm_at_a_random_moment_of_a_session_leaves_a_bvh_and_a_summary_that_load(tmp_path):
    rng = np.random.default_rng(55)
    for attempt in range(10):
        folder = tmp_path / f"try{attempt}"
        folder.mkdir()
        with Devices() as devices:
            devices.config(folder)
            with open(folder / "board.toml", "a") as f:
                f.write('\n[output]\nbvh = "out/take.bvh"\n\n[runtime]\nsamples = 2\nlookahead = 2\nadaptive = false\n')
            proc = started(folder)
            take = folder / "out/take.bvh"
            try:
                # streaming: the first rows past the header have reached the file (Python's buffer, ~12 frames)
                assert wait_until(lambda take=take: take.exists() and take.stat().st_size > 9000, 60, proc), proc.stderr.read()
                time.sleep(rng.uniform(0.0, 2.0))
                proc.send_signal(signal.SIGTERM)
                _, err = proc.communicate(timeout=20)
            finally:
                if proc.poll() is None:
                    proc.kill()
        assert proc.returncode == 0, err
        assert "stopped by SIGTERM" in err
        summary = json.loads((folder / "out/run.json").read_text())
        clip = bvh.load(take)
        assert clip.frames == summary["frames_out"] > 10, (clip.frames, summary["frames_out"])


def test_sigterm_during_a_recording_keeps_what_was_recorded(tmp_path):
    from edgetools.sim.session import Session
    with Devices() as devices:
        devices.config(tmp_path)
        proc, err = sigterm_after(4.0, tmp_path, "record", "--config", "board.toml", "--seconds", 60, "--out", "take.npz")
    assert proc.returncode == 0 and "stopped by SIGTERM" in err, err
    session = Session.load(tmp_path / "take.npz")
    assert len(session.headset.frames) > 30 and len(session.hub.frames) > 30
    assert not list(tmp_path.glob(".take*"))            # no temporary file left beside it


def test_sigterm_during_calibration_leaves_the_previous_calibration(tmp_path):
    previous = Calibration(1.05)
    previous.save(tmp_path / "cal.json")
    before = (tmp_path / "cal.json").read_bytes()
    with Devices() as devices:
        devices.config(tmp_path)
        proc, err = sigterm_after(4.0, tmp_path, "calibrate", "--config", "board.toml", "--seconds", 30, "--out", "cal.json")
    assert proc.returncode == 130 and "is as it was" in err, err
    assert (tmp_path / "cal.json").read_bytes() == before


def test_a_write_cut_short_leaves_the_old_calibration_whole(tmp_path, monkeypatch):
    path = tmp_path / "cal.json"
    Calibration(1.05).save(path)
    before = path.read_bytes()
    real_write = type(path).write_text

    def cut_short(self, text, *a, **k):
        real_write(self, text[:len(text) // 2])
        raise OSError("no space left on device")
    monkeypatch.setattr(type(path), "write_text", cut_short)
    with pytest.raises(OSError):
        Calibration(0.93).save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and Calibration.load(path).height_scale == pytest.approx(1.05)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]
    Calibration(0.93).save(path)
    assert Calibration.load(path).height_scale == pytest.approx(0.93)


def test_stop_signals_turn_sigterm_and_ctrl_c_into_a_request_and_put_the_handlers_back():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with StopSignals() as stop:
        assert not stop.requested()
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGTERM)            # a second one while going down changes nothing
        assert stop.requested() and stop.signal_name == "SIGINT"
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_replace_whole_keeps_the_old_file_when_the_writer_fails(tmp_path):
    path = tmp_path / "out" / "take.npz"
    with replace_whole(path) as tmp:
        tmp.write_bytes(b"first")
    with pytest.raises(ValueError), replace_whole(path) as tmp:
        tmp.write_bytes(b"sec")
        raise ValueError("the writer failed")
    assert path.read_bytes() == b"first" and [p.name for p in path.parent.iterdir()] == ["take.npz"]
