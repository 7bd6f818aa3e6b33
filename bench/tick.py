"""The board tick part by part: what a tick costs outside the pipeline, against the pipeline's step.

    python bench/tick.py [--samples 16] [--precision int8] [--ticks 3000] [--blocks 10] [--against REV] [--json OUT]

Runs the board's service (`edge run`'s Service) fed one headset and one waist sample a tick in-process
(edgetools.profile's Feeder, as `edge profile` does), unpaced, in a worker pinned to one core, and
times each tick's parts (bench/tick_worker.py): poll (the sources' samples into the synchroniser),
sync (the synchroniser's frame), step (Pipeline.step), emit (encoding and sending the pose, recording
its age) and the whole Service.step. "outside" is the whole tick less the step. With --against REV the
same runs on another git revision's tree in a second worker, in turns block by block (A B, B A, ...),
so both see the same machine. Prints p50 (p99) microseconds and the ratios measured in this one run;
#32's line is outside / step <= 0.5 at the board's default N (16).
"""
import argparse
import io
import json
import os
import platform
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent
PARTS = ("poll", "sync", "step", "emit", "tick")
WARMUP = 300


def cpu_name():
    try:
        return next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor()


def worker(tree, n, precision, core):
    env = dict(os.environ, PYTHONPATH=str(tree))
    p = subprocess.Popen(["taskset", "-c", str(core), sys.executable, str(HERE / "bench" / "tick_worker.py"), str(n),
                          precision, str(WARMUP)], cwd=tree, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         text=True)
    json.loads(p.stdout.readline())
    return p


def run(trees, n, precision, ticks, blocks):
    """{side: {part: [ticks] microseconds}}, the sides taking turns block by block."""
    core = min(os.sched_getaffinity(0))
    procs = {side: worker(tree, n, precision, core) for side, tree in trees.items()}
    per = ticks // blocks
    times = {side: {part: [] for part in PARTS} for side in trees}
    try:
        for b in range(blocks):
            for side in (list(trees) if b % 2 == 0 else list(trees)[::-1]):
                procs[side].stdin.write(f"tick {per}\n")
                procs[side].stdin.flush()
                got = json.loads(procs[side].stdout.readline())
                for part in PARTS:
                    times[side][part].append(got[part])
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait()
    return {side: {part: np.array(v) for part, v in parts.items()} for side, parts in times.items()}


def describe(t):
    """Per part p50 / p99, the outside (tick less step) and its ratio to the step, per side."""
    outside = t["tick"] - t["step"]
    out = {part: {"p50": float(np.median(t[part])), "p99": float(np.percentile(t[part], 99))} for part in PARTS}
    out["outside"] = {"p50": float(np.median(outside)), "p99": float(np.percentile(outside, 99))}
    out["outside_over_step"] = float(np.median(outside) / np.median(t["step"]))
    # per block, so a reader sees how steady the ratio was
    blocks = np.median(outside, axis=1) / np.median(t["step"], axis=1)
    out["outside_over_step_blocks"] = [float(blocks.min()), float(blocks.max())]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=16, help="N (default 16: the board config's)")
    ap.add_argument("--precision", choices=("fp32", "int8"), default="int8")
    ap.add_argument("--ticks", type=int, default=3000)
    ap.add_argument("--blocks", type=int, default=10)
    ap.add_argument("--against", metavar="REV", help="another git revision, timed in turns with this tree")
    ap.add_argument("--json")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"this": HERE}
        if a.against:
            arch = subprocess.run(["git", "archive", a.against], cwd=HERE, check=True, capture_output=True).stdout
            with tarfile.open(fileobj=io.BytesIO(arch)) as tar:
                tar.extractall(tmp, filter="data")
            rev = subprocess.run(["git", "rev-parse", "--short", a.against], cwd=HERE, check=True, capture_output=True,
                                 text=True).stdout.strip()
            trees[rev] = Path(tmp)
        times = run(trees, a.samples, a.precision, a.ticks, a.blocks)
    sides = {side: describe(t) for side, t in times.items()}
    print(f"the board tick at N={a.samples}, {a.precision}, one core of {cpu_name()}; p50 (p99) microseconds, "
          f"{a.ticks} ticks in {a.blocks} blocks" + (" taken in turns" if a.against else ""))
    print(f"{'side':>8} " + " ".join(f"{p:>13}" for p in (*PARTS, "outside")) + "  outside/step [blocks]")
    for side, d in sides.items():
        print(f"{side:>8} " + " ".join(f"{d[p]['p50']:>6.0f} ({d[p]['p99']:>4.0f})" for p in (*PARTS, "outside"))
              + f"  {d['outside_over_step']:.2f} [{d['outside_over_step_blocks'][0]:.2f}, {d['outside_over_step_blocks'][1]:.2f}]")
    report = {"samples": a.samples, "precision": a.precision, "ticks": a.ticks, "blocks": a.blocks, "cpu": cpu_name(),
              "sides": sides}
    if a.against:
        this, other = times["this"], times[rev]
        report["this_over_against"] = {p: float(np.median(this[p]) / np.median(other[p])) for p in PARTS}
        print(f"this / {rev}: " + ", ".join(f"{p} {v:.2f}" for p, v in report["this_over_against"].items()))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
