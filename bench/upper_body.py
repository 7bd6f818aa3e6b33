"""The arms a user sees, on val: upper-body errors and the elbows' smoothness, for a model folder.

    python bench/upper_body.py [--data ../shared/mocap] [--models DIR] [--people unseen|seen|all]
        [--precision int8|fp32] [--samples 1] [--elbow-from-hand G] [--bend FLEX,DEV] [--smooth HZ,BETA]
        [--max-clips K] [--numpy] [--out out/upper_body]

Runs edge eval (N=1 by default, the 4-point case) with a dump of every clip, then prints, per joint
(collars, shoulders, elbows, wrists), the mean position error; the elbows' jerk (mean magnitude of the
third difference, m/s^3) against the truth's on the same frames; and how many frames put an elbow
inside the torso (closer than TORSO_RADIUS_M to the pelvis-spine-chest-neck line, between pelvis and
neck height), in the prediction and in the truth. Writes summary.json beside the eval's JSON.

--elbow-from-hand sets edge.ik.swivel_to_hands' gain (0: the decoder's own elbow side). --bend bends
the controllers' hands at the wrist (motion.synth.bend_hands: flexion and deviation std, degrees):
val's hands are CMU's and Daz's, which hardly bend against the forearm (python -m motion.hands), and a
person's do. --smooth sets the upper body's one-euro filter (edge.smooth: its cut-off floor in Hz and
its rise with speed; 0,0: off).
"""
import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from edge.ik import closest_on_polyline
from edge.inference import DEFAULT_PRECISION
from edge.options import PipelineOptions
from edge.skeleton import JOINT
from motion.evaluate import evaluate

ARM_JOINTS = ("l_collar", "r_collar", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist")
ELBOWS = [JOINT["l_elbow"], JOINT["r_elbow"]]
TORSO = [JOINT[n] for n in ("pelvis", "spine", "chest", "neck")]
TORSO_RADIUS_M = 0.10          # a slim torso's half-depth: an elbow closer to the spine line is inside it


def point_to_polyline(p, line):
    """Distance from points p [T,K,3] to the polyline line [T,L,3] -> [T,K]."""
    return np.linalg.norm(p - closest_on_polyline(p, line), axis=-1)


def elbows_inside_torso(pos):
    """[T] bool: an elbow within TORSO_RADIUS_M of the torso line, between pelvis and neck height."""
    line = pos[:, TORSO]
    elbows = pos[:, ELBOWS]
    near = point_to_polyline(elbows, line) < TORSO_RADIUS_M
    y = elbows[..., 1]
    between = (y > line[:, :1, 1]) & (y < line[:, -1:, 1])
    return (near & between).any(-1)


def jerk(pos, fps):
    """Mean magnitude of the third difference of pos [T,K,3] (m/s^3), per frame [T-3]."""
    return np.linalg.norm(np.diff(pos, n=3, axis=0) * fps ** 3, axis=-1).mean(-1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--models", default=None)
    ap.add_argument("--people", choices=("unseen", "seen", "all"), default="unseen")
    ap.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--elbow-from-hand", type=float, default=None)
    ap.add_argument("--bend", default=None, help="FLEX,DEV: the hands' bend std in degrees")
    ap.add_argument("--smooth", default=None, help="MIN_CUTOFF_HZ,BETA: the upper body's one-euro filter "
                                                   "(edge.smooth; 0,0: off)")
    ap.add_argument("--max-clips", type=int, default=None)
    ap.add_argument("--numpy", action="store_true", help="the numpy reference frame, not the compiled core")
    ap.add_argument("--out", default="out/upper_body")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="upper-body-") as dump:
        opts = PipelineOptions(samples=a.samples, precision=a.precision, use_native=not a.numpy)
        if a.elbow_from_hand is not None:
            opts = replace(opts, elbow_from_hand=a.elbow_from_hand)
        if a.smooth:
            cut, beta = (float(x) for x in a.smooth.split(","))
            opts = replace(opts, smooth_min_cutoff=cut, smooth_beta=beta)
        bend = tuple(float(x) for x in a.bend.split(",")) if a.bend else None
        r = evaluate([a.data], opts, split="val", people=None if a.people == "all" else a.people, models=a.models,
                     max_clips=a.max_clips, hand_bend=bend, dump=dump, log=lambda *x: None)
        jp, jg, inside_p, inside_g, frames = [], [], 0, 0, 0
        for f in sorted(Path(dump).glob("*.npz")):
            d = np.load(f)
            w, fps = int(d["warmup_frames"]), float(d["fps"])
            pred, gt = d["pred_pos"][w:].astype(np.float64), d["gt_pos"][w:].astype(np.float64)
            if len(pred) < 8:
                continue
            jp.append(jerk(pred[:, ELBOWS], fps))
            jg.append(jerk(gt[:, ELBOWS], fps))
            inside_p += int(elbows_inside_torso(pred).sum())
            inside_g += int(elbows_inside_torso(gt).sum())
            frames += len(pred)
    per_joint = dict(zip(r["joint_names"], r["per_joint_mpjpe_cm"], strict=True))
    jp, jg = np.concatenate(jp), np.concatenate(jg)
    summary = {"people": a.people, "clips": r["clips"], "frames": frames, "mpjpe_cm": r["mpjpe_cm"],
               "joints_cm": {n: per_joint[n] for n in ARM_JOINTS},
               "elbow_jerk_m_s3": float(jp.mean()), "truth_elbow_jerk_m_s3": float(jg.mean()),
               "elbow_jerk_ratio": float(jp.mean() / jg.mean()),
               "elbow_inside_torso_frames": inside_p, "truth_elbow_inside_torso_frames": inside_g,
               "models": a.models or "models/", "precision": r["precision_in_use"], "samples": a.samples,
               "elbow_from_hand": opts.elbow_from_hand, "hand_bend_std_deg": bend,
               "smooth": [opts.smooth_min_cutoff, opts.smooth_beta]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"val, {a.people} people, N={a.samples}, {r['precision_in_use']}, elbow from hand {opts.elbow_from_hand:g}, "
          f"smoothing {opts.smooth_min_cutoff:g} Hz + {opts.smooth_beta:g}/speed, hand bend {bend or 'none'}: {r['clips']} clips, {frames} frames, mpjpe {r['mpjpe_cm']:.3f} cm")
    for side in ("l", "r"):
        print("  " + "  ".join(f"{n}: {per_joint[n]:.2f} cm" for n in ARM_JOINTS if n.startswith(side)))
    print(f"  elbow jerk {jp.mean():.0f} m/s^3 against the truth's {jg.mean():.0f} ({jp.mean() / jg.mean():.2f}x); "
          f"frames with an elbow inside the torso: {inside_p} (truth {inside_g})")
    print(f"wrote {out}/summary.json")


if __name__ == "__main__":
    main()
