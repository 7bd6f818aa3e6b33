"""`edge ssi-study`: SSI's application criteria (section 5.3, Table 3) on clips with kicks or near obstacles.

high-kick / low-kick: at each kick apex found in the ground truth, a target sits at the true foot
position; the runtime sees the target from 20 frames before the apex (TargetHit, eq. 3) and we
measure the distance from the predicted foot to it at the apex. avoid: a sphere beside the left
knee; the runtime avoids it (CollisionAvoid, eq. 4) and we measure the fraction of frames in which a
predicted left-leg joint is inside it.
"""
import json
import sys
from pathlib import Path

import numpy as np

from motion.bvh import BvhError
from edge.criteria import CollisionAvoid, TargetHit
from motion.evaluate import run_take
from edge.inference import DEFAULT_PRECISION
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.progress import Progress
from edge.skeleton import JOINT
from motion.takes import find_clips, load_take

KICK_HEIGHTS = {"high-kick": (0.9, 3.0), "low-kick": (0.35, 0.9)}   # toe height at the apex, metres
LEAD_FRAMES = 20
TARGET_RADIUS_M = 0.02      # with --refine: how close counts as reached
LEFT_LEG = ("l_knee", "l_ankle", "l_toe")


def kick_apexes(gt_pos, task, min_gap=45):
    """(frame, toe joint) of kick apexes: local maxima of toe height within the task's height band."""
    lo, hi = KICK_HEIGHTS[task]
    events = []
    for name in ("l_toe", "r_toe"):
        j = JOINT[name]
        h = gt_pos[:, j, 1]
        for t in range(LEAD_FRAMES, len(h) - 5):
            win = h[max(t - 15, 0):t + 16]
            if lo <= h[t] < hi and h[t] == win.max() and h[t] - win.min() > 0.2:
                if not events or t - events[-1][0] >= min_gap or events[-1][1] != j:
                    events.append((t, j))
    return sorted(events)


def obstacle_for(take):
    """A 12 cm sphere 25 cm to the left of the left knee at mid-clip (where the truth does not go)."""
    mid = take.frames // 2
    hips = take.gt_pos[mid, JOINT["l_hip"]] - take.gt_pos[mid, JOINT["r_hip"]]
    left = hips / np.linalg.norm(hips)
    return take.gt_pos[mid, JOINT["l_knee"]] + 0.25 * left, 0.12


def run_study(paths, task, samples_list, runs, split=None, models=None, max_clips=None, log=print,
              precision=DEFAULT_PRECISION, refine=None):
    takes = []
    for f in find_clips(paths, split):
        try:
            take = load_take(f)
        except BvhError as e:
            log(f"skipped: {e}")
            continue
        if task == "avoid" or kick_apexes(take.gt_pos, task):
            takes.append(take)
        if max_clips and len(takes) >= max_clips:
            break
    if not takes:
        raise SystemExit(f"edge ssi-study: no clip in {paths} has a {task} event")
    results = []
    with Progress(len(samples_list) * runs * len(takes), f"ssi-study {task}") as bar:
        for n in samples_list:
            values, gt_values, mpjpe = [], [], []
            for r in range(runs):
                for take in takes:
                    value, gt_value, m = _one(take, task, n, r, models, precision, refine)
                    values += value
                    gt_values += gt_value
                    mpjpe.append(m)
                    bar.update()
            v = np.array(values)
            results.append({"samples": n, "mean": float(v.mean()), "std": float(v.std()), "runs": runs,
                            "mpjpe_cm": 100 * float(np.mean(mpjpe)),
                            "events": len(v) // runs, **({"ground_truth_rate": float(np.mean(gt_values))}
                                                         if task == "avoid" else {})})
            log(f"N={n}: mean {v.mean():.4f} std {v.std():.4f} over {len(v)} measurements; "
                f"takes' mpjpe {100 * np.mean(mpjpe):.2f} cm")
    unit = "collision rate (fraction of frames)" if task == "avoid" else "distance to target (m)"
    return {"task": task, "unit": unit, "clips": [t.name for t in takes], "results": results}


def _one(take, task, n, seed, models, precision=DEFAULT_PRECISION, refine=None):
    pipe = Pipeline(PipelineOptions(samples=n, seed=seed, precision=precision, refine=refine), models=models)   # the default criteria, plus the task's
    if task == "avoid":
        center, radius = obstacle_for(take)
        crit = CollisionAvoid([center], [radius], joints=LEFT_LEG, weight=10.0)
        pipe.criteria.criteria.append(crit)
        pred = run_take(pipe, take).pred
        return ([float(np.mean(crit.penetration(pred) > 0))], [float(np.mean(crit.penetration(take.gt_pos) > 0))],
                take_mpjpe(pred, take))
    events = kick_apexes(take.gt_pos, task)
    active = {}
    for t, j in events:
        for f in range(t - LEAD_FRAMES, t + 1):
            active[f] = (j, take.gt_pos[t, j])
    for joint in {j for _, j in events}:
        pipe.criteria.criteria.append(TargetHit(joint, lambda f, joint=joint: active[f][1] if f in active and active[f][0] == joint else None,
                                                weight=10.0))
    if pipe.refiner is not None:        # the refiner reaches for each target over its window (TARGET_RADIUS_M)
        for t, j in events:
            pipe.refiner.add_target(int(j), take.gt_pos[t, j], radius=TARGET_RADIUS_M, first=t - LEAD_FRAMES, last=t)
    pred = run_take(pipe, take).pred
    return [float(np.linalg.norm(pred[t, j] - take.gt_pos[t, j])) for t, j in events], [], take_mpjpe(pred, take)


def take_mpjpe(pred, take):
    """The take's mean joint error (m), after the first second (warm-up, as `edge eval` skips it)."""
    s = int(round(take.fps))
    return float(np.linalg.norm(pred[s:] - take.gt_pos[s:], axis=-1).mean())


def main(args):
    samples = [int(x) for x in args.samples.split(",")]
    from edgetools.eval import refine_settings
    result = run_study(args.data, args.task, samples, args.runs, args.split, args.models, args.max_clips,
                       refine=refine_settings(args))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}", file=sys.stderr)
    return 0
