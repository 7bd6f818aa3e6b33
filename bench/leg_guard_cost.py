"""What the foot IK's leg guard (edge.ik.guard_legs) does to the board's frame, on the bundled walk.

    python bench/leg_guard_cost.py [--samples 16] [--passes 6] [--precision int8] [--figure PNG]

Two pipelines at the board's settings (N = --samples, int8, refinement at its defaults, so LegsApart
is armed from each shown pose): the leg guard at its default and off (leg_guard=0). They take turns,
one pass over the walk at a time, pinned to one core in this process. Prints each one's frame time
(p50, p99, mean over all passes), the share of frames LegsApart was armed and the leg crossings of the
shown pose, and guard / off. A benchmark, not a test: it prints figures and asserts nothing.
--figure (needs the viz extra) also draws the walk at N=1 where its legs come closest without the
guard: the truth beside the prediction, guard off above, guard on below (docs/img/leg_guard.png).
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
        armed.append(pipe.refiner.term("legs").armed)
        if pose is not None:
            gaps.append(leg_gap(pose.positions))


def figure(take, path):
    """The six frames whose unguarded legs come closest (at least 20 frames apart), truth beside the
    prediction, without the guard and with it, one strip above the other."""
    from PIL import Image

    from edge.skeleton import JOINT_NAMES, PARENTS
    from motion.evaluate import run_take
    from viz.canvas import fit_width, save_png
    from viz.figures import skeleton_strip
    runs = {g: run_take(Pipeline(PipelineOptions(samples=1, refine={"steps": 2}, leg_guard=g)), take).pred
            for g in (0.0, LEG_GUARD_M)}
    gap = leg_gap(runs[0.0])
    gap[:60] = np.inf
    frames = []
    for t in np.argsort(gap):
        if len(frames) == 6:
            break
        if all(abs(int(t) - f) >= 20 for f in frames):
            frames.append(int(t))
    frames.sort()
    strips = []
    for g, label in ((0.0, "guard off"), (LEG_GUARD_M, f"guard {LEG_GUARD_M * 100:.0f} cm")):
        out = Path(path).with_suffix(f".{int(g * 100)}.png")
        gaps = ", ".join(f"{100 * leg_gap(runs[g][f]):.0f}" for f in frames)
        skeleton_strip(take.gt_pos, runs[g], PARENTS, list(JOINT_NAMES), take.fps, frames, out,
                       title=f"{take.name}, {label}: legs {gaps} cm apart")
        strips.append(np.asarray(Image.open(out).convert("RGB")))
        out.unlink()
    width = max(s.shape[1] for s in strips)
    save_png(np.concatenate([fit_width(s, width) for s in strips], axis=0), path)
    print(f"wrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--passes", type=int, default=6, help="timed passes per side (0: the figure only)")
    ap.add_argument("--precision", default="int8")
    ap.add_argument("--figure", metavar="PNG", help="also draw the walk's closest legs, guard off and on")
    a = ap.parse_args()
    take = from_sample(SAMPLE)
    if a.figure:
        figure(take, a.figure)
    if a.passes < 1:
        return
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
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
