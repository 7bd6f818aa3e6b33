"""Each `edge` subcommand run as a user runs it: a subprocess (`python -m edgetools.cli`, what the `edge`
script calls) on the bundled sample and session, simulated devices on real ptys where a board would have
hardware, with short bounded runs. Checks the exit code, what the command prints and the files it says
it writes; the functions behind the commands have their own tests."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "cmu_09_12_walk.npz"
SESSION = ROOT / "samples" / "cmu_09_12_walk.session.npz"


def edge(*args, cwd, timeout=120, env=None):
    """`edge ARGS...` in `cwd`; the CompletedProcess (text stdout and stderr)."""
    return subprocess.run([sys.executable, "-m", "edgetools.cli", *map(str, args)], cwd=cwd, capture_output=True,
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
