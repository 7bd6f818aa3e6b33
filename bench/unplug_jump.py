"""Does the pose pop when a foot tracker is unplugged? (the variable-sensor-set issue)

    python bench/unplug_jump.py [--data ../shared/mocap] [--trackers l_foot,r_foot] [--unplug l_foot] [--at 4]

Feeds takes through the default pipeline with the extra IMUs worn; at --at seconds the --unplug tracker
goes silent for good and the synchroniser's hold-and-fade (edge.imus.fade, what FrameSynchronizer does
per tick) takes it out. Per take it measures the largest frame-to-frame move of any joint of the output
in the second after the loss and in the second before it, and prints both and their ratio. Without
--data it uses the bundled walk; with it, every val clip long enough.
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from motion.evaluate import run_take
from edge.imus import IMU_INDEX, ImuNoise, mask, parse_set
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from motion.synth import wear
from motion.takes import find_clips, load_take

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"


def jumps(take, pipe, worn_names, unplug, at_s, seed=0, control=False):
    """(largest joint step in the second before at_s, in the second after); control=True keeps every
    tracker: how much the motion itself changes between the two seconds."""
    fps, T = take.fps, take.frames
    worn = mask(worn_names)
    alive = np.repeat(worn[None] > 0, T, axis=0)
    t0 = int(at_s * fps)
    if not control:
        alive[t0:, IMU_INDEX[unplug]] = False
    sig = wear(take.signals, worn, fps, np.random.default_rng(seed), ImuNoise(), alive)
    pred = run_take(pipe, take, signals=sig).pred
    step = np.linalg.norm(np.diff(pred, axis=0), axis=-1).max(-1)      # largest joint move per frame [T-1]
    w = int(fps)
    return float(step[t0 - w:t0].max()), float(step[t0:t0 + w].max())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="a mocap folder (val clips) instead of the bundled walk")
    ap.add_argument("--trackers", default="l_foot,r_foot")
    ap.add_argument("--unplug", default="l_foot")
    ap.add_argument("--at", type=float, default=4.0)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--json")
    a = ap.parse_args()
    names = parse_set(a.trackers)
    if a.unplug not in names:
        ap.error(f"--unplug {a.unplug} is not among --trackers {a.trackers}")
    pipe = Pipeline(PipelineOptions(samples=a.samples))
    files = find_clips([a.data], "val") if a.data else [SAMPLE]
    rows = []
    for f in files:
        take = load_take(f)
        if take.frames < (a.at + 1.5) * take.fps:
            continue
        before, after = jumps(take, pipe, names, a.unplug, a.at)
        c_before, c_after = jumps(take, pipe, names, a.unplug, a.at, control=True)
        rows.append({"clip": str(f), "before_m": before, "after_m": after, "ratio": after / before,
                     "control_ratio": c_after / c_before, "after_vs_control": after / c_after})
        print(f"{Path(f).name:40} before {before * 100:6.2f} cm  after {after * 100:6.2f} cm  ratio {after / before:5.2f}"
              f"  (kept: {c_after / c_before:5.2f}; after / kept's after {after / c_after:5.2f})")
    r = np.array([x["ratio"] for x in rows])
    c = np.array([x["control_ratio"] for x in rows])
    v = np.array([x["after_vs_control"] for x in rows])
    print(f"{len(rows)} takes: ratio median {np.median(r):.2f}, max {r.max():.2f}, over 1.5 in {int((r > 1.5).sum())}; "
          f"with the tracker kept: median {np.median(c):.2f}, over 1.5 in {int((c > 1.5).sum())}; "
          f"largest step after the loss / with it kept: median {np.median(v):.2f}, max {v.max():.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps({"rows": rows, "median_ratio": float(np.median(r)),
                                            "max_ratio": float(r.max()), "control_median_ratio": float(np.median(c)),
                                            "after_vs_control_max": float(v.max())}, indent=2) + "\n")


if __name__ == "__main__":
    main()
