"""How much of a body's error its proportions would take away (issue #54, items 2-3): the runtime's poses
on bodies with legs long or short for their height, scored as they are (the canonical skeleton scaled by
height, what the board sends today) and with the same joint angles put on the body's own skeleton (the
limbs as an ideal measurement would give them), hung from the tracked head as the runtime hangs it.

    python bench/bodies_oracle.py [--data ../shared/mocap] [--max-clips 40] [--max-frames 900]

Prints, per body, mpjpe and knees and ankles (cm) both ways, on val's unseen people, int8, N = 1.
"""
import argparse
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from edge.calibration import devices_on_canonical
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.skeleton import HEAD, JOINT, fk
from motion.bodies import Body, CANONICAL
from motion.evaluate import WARMUP_S, _clips, body_take, on_canonical_scale

KNEES = [JOINT["l_knee"], JOINT["r_knee"]]
ANKLES = [JOINT["l_ankle"], JOINT["r_ankle"]]


def run_body(pipe, files, body, max_frames):
    """(as sent, on the body's skeleton): summed errors [3] (mpjpe, knees, ankles) and frames."""
    scale, offsets = on_canonical_scale(body), body.offsets()
    sums, n = np.zeros((2, 3)), 0
    for f in files:
        take = body_take(f, body)
        sig = take.signals
        fed = replace(sig, **dict(zip(("head_pos", "hand_pos"), devices_on_canonical(
            sig.head_pos, sig.head_rot, sig.hand_pos, sig.hand_rot, scale), strict=True)))
        T = min(take.frames, max_frames)
        pos = np.zeros((T, len(offsets), 3))
        rot = np.zeros((T, len(offsets), 3, 3))
        pipe.reset()
        for t in range(T):
            pose = pipe.step(fed.slice(t, t + 1))
            if pose is not None:
                pos[pose.frame], rot[pose.frame] = pose.positions, pose.rotations
        for pose in pipe.flush():
            pos[pose.frame], rot[pose.frame] = pose.positions, pose.rotations
        w = int(round(WARMUP_S * take.fps))
        sent = pos / scale
        _, own = fk(rot, np.zeros((T, 3)), offsets=offsets)
        own += (sent[:, HEAD] - own[:, HEAD])[:, None]          # hung from the tracked head, as the runtime does
        for k, p in enumerate((sent, own)):
            err = np.linalg.norm(p[w:] - take.gt_pos[w:T], axis=-1)
            sums[k] += [err.mean(1).sum(), err[:, KNEES].mean(1).sum(), err[:, ANKLES].mean(1).sum()]
        n += T - w
    return sums * 100 / n, n


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--max-clips", type=int, default=40)
    ap.add_argument("--max-frames", type=int, default=900)
    a = ap.parse_args()
    files = _clips([a.data], "val", a.max_clips, "unseen")
    pipe = Pipeline(PipelineOptions(samples=1, precision="int8"))
    bodies = [CANONICAL] + [Body(f"1.75 m, legs {legs:g}x", 1.75, legs) for legs in (0.92, 1.0, 1.08)]
    print(f"{len(files)} clips of val's unseen people, int8, N = 1; cm: mpjpe / knees / ankles")
    for body in bodies:
        (sent, own), frames = run_body(pipe, files, body, a.max_frames)
        print(f"{body.name:<22} as sent {sent[0]:.2f} / {sent[1]:.2f} / {sent[2]:.2f}   on its own skeleton "
              f"{own[0]:.2f} / {own[1]:.2f} / {own[2]:.2f}   ({frames} frames)", flush=True)


if __name__ == "__main__":
    main()
