"""What the foot IK's leg guard (edge.ik.guard_legs) does to the board's frame, on the bundled walk.

    python bench/leg_guard_cost.py [--samples 16] [--passes 6] [--precision int8]

Two pipelines at the board's settings (N = --samples, int8, refinement at its defaults, so LegsApart
is armed from each shown pose): the leg guard at its default and off (leg_guard=0). They take turns,
one pass over the walk at a time, pinned to one core in this process. Prints each one's frame time
(p50, p99, mean over all passes), the share of frames LegsApart was armed and the leg crossings of the
shown pose, and guard / off. A benchmark, not a test: it prints figures and asserts nothing.
"""
import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.options import PipelineOptions
from edge.physics import INTERSECT_M, LEG_GUARD_M, leg_gap
from edge.pipeline import Pipeline
from motion.takes import from_sample

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"


def one_pass(pipe, sig, T, times, armed, gaps):
    pipe.reset()
    for t in range(T):
        frame = sig.slice(t, t + 1)
        t0 = time.perf_counter_ns()
        pose = pipe.step(frame)
        times.append(time.perf_counter_ns() - t0)
        armed.append(pipe._legs is not None and pipe._legs.armed)
        if pose is not None:
            gaps.append(leg_gap(pose.positions))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--passes", type=int, default=6)
    ap.add_argument("--precision", default="int8")
    a = ap.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    take = from_sample(SAMPLE)
    sides = {}
    for name, guard in (("guard", LEG_GUARD_M), ("off", 0.0)):
        pipe = Pipeline(PipelineOptions(samples=a.samples, precision=a.precision, refine={"steps": 2}, leg_guard=guard))
        sides[name] = (pipe, [], [], [])
        one_pass(pipe, take.signals, 120, [], [], [])          # warm-up
    for _ in range(a.passes):
        for name in sides:
            pipe, times, armed, gaps = sides[name]
            one_pass(pipe, take.signals, take.frames, times, armed, gaps)
    print(f"bundled walk, {take.frames} frames x {a.passes} passes, N={a.samples}, {a.precision}, refinement on, one core")
    print("side    p50 us  p99 us  mean us  LegsApart armed  crossing frames")
    figs = {}
    for name, (_, times, armed, gaps) in sides.items():
        us = np.array(times) / 1e3
        figs[name] = (np.percentile(us, 50), np.percentile(us, 99), us.mean())
        print(f"{name:6s} {figs[name][0]:7.0f} {figs[name][1]:7.0f} {figs[name][2]:8.0f} {100 * np.mean(armed):15.1f} % "
              f"{100 * np.mean(np.array(gaps) < INTERSECT_M):14.2f} %")
    r = [g / o for g, o in zip(figs["guard"], figs["off"], strict=True)]
    print(f"guard / off: p50 {r[0]:.2f}x, p99 {r[1]:.2f}x, mean {r[2]:.2f}x")


if __name__ == "__main__":
    main()
