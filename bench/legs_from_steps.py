"""The legs' length from a user's steps, with thigh and shin IMUs (#54 item 2, the second approach; the answer
measured: not within 2 cm).

bench/legs_from_movement.py tried the head's height: the body keeps the head where the stature puts it,
so it barely moves with `legs`. Steps move it sideways instead, by as much as the legs are long. While
a foot is planted, the head joint is that ankle plus the leg and the trunk:

    head(t) = ankle - legs L(t) + tau T(t)   =>   d head = -legs dL + tau dT      (d ankle = 0)

with L the pelvis -> ankle vector and T the pelvis -> head vector on the canonical bones, from the
IMUs' segment directions (waist = pelvis, thigh, shin; the spine, chest and neck between the waist and
the headset, or the chest IMU with --chest). Every planted stretch of STEP_S is a 3-vector equation in
`legs` and the trunk's scale `tau`; least squares over the first minute. (Tying tau to legs, as the
stature does, multiplies T's errors by 2.5: worse.) SlimeVR's AutoBone fits the same kind of constraint
(a planted foot does not slide) to a recording of the user. The planted foot: the ankle (on the legs
estimated so far, canonical first) slower than PLANTED_M_S; two passes; or,
with --truth-stance, the truth's ankles slower than 0.1 m/s (the most a contact detector could give).

    python bench/legs_from_steps.py [--clips 12] [--chest] [--no-noise] [--truth-stance] [--seconds 60]

Prints per body the median estimate and each clip's error in thigh + shin (cm, on the body's own size),
then how many are within 2 cm. Measured (8 December, 12 clips of val's unseen people, 9 bodies): see
models/MODEL_CARD.md, "People of every size and shape". With the true trunk and true contacts the
equation holds to 1 % (the script's premise); what breaks it is the trunk between the waist and the
head, which no worn sensor measures: its error in dT is as large as a step's dL.
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from edge import quat
from edge.calibration import devices_on_canonical
from edge.imus import IMU_INDEX, ImuNoise
from edge.signals import EYE_OFFSET
from edge.skeleton import JOINT, OFFSETS
from motion.bodies import Body, take_on
from motion.evaluate import _clips, on_canonical_scale, take_signals
from motion.retarget import load_motion
from motion.takes import FPS

PLANTED_M_S = 0.25          # an ankle slower than this (horizontally) is planted
STEP_S = 0.25               # each equation: the change over this long, inside one planted stretch
LEGS_IMUS = ("l_thigh", "r_thigh", "l_shin", "r_shin")


def vectors(sig, scale, chest_imu):
    """Per frame: the head joint [T,3] (canonical units), the trunk T [T,3] and each leg's L [T,2,3]."""
    head_pos, _ = devices_on_canonical(sig.head_pos, sig.head_rot, sig.hand_pos, sig.hand_rot, scale)
    head = head_pos - quat.rotate(sig.head_rot, EYE_OFFSET)
    pelvis, imu = quat.to_matrix(sig.waist_rot), quat.to_matrix(sig.imu_rot)
    chest_q = sig.imu_rot[:, IMU_INDEX["chest"]] if chest_imu else quat.slerp(sig.waist_rot, sig.head_rot, 0.5)
    spine = quat.to_matrix(quat.slerp(sig.waist_rot, chest_q, 0.5))
    neck = quat.to_matrix(quat.slerp(chest_q, sig.head_rot, 0.5))
    trunk = (pelvis @ OFFSETS[JOINT["spine"]] + spine @ OFFSETS[JOINT["chest"]]
             + quat.to_matrix(chest_q) @ OFFSETS[JOINT["neck"]] + neck @ OFFSETS[JOINT["head"]])
    legs = np.stack([pelvis @ OFFSETS[JOINT[f"{s}_hip"]] + imu[:, IMU_INDEX[f"{s}_thigh"]] @ OFFSETS[JOINT[f"{s}_knee"]]
                     + imu[:, IMU_INDEX[f"{s}_shin"]] @ OFFSETS[JOINT[f"{s}_ankle"]] for s in "lr"], axis=1)
    return head, trunk, legs


def planted(head, trunk, legs_vec, legs, tau, fps):
    """[T,2] bool: each ankle (on `legs`, `tau`) slower than PLANTED_M_S."""
    ankle = (head - tau * trunk)[:, None] + legs * legs_vec
    k = max(1, int(round(STEP_S * fps)))       # over a stretch: a frame's IMU jitter alone reads as 0.5 m/s
    speed = np.zeros(ankle.shape[:2])
    speed[k:] = np.linalg.norm(ankle[k:, :, [0, 2]] - ankle[:-k, :, [0, 2]], axis=-1) / STEP_S
    return speed < PLANTED_M_S


def equations(head, trunk, legs_vec, still, fps):
    """(d head [3E], [-dL, dT] [3E,2]) over each planted stretch of STEP_S."""
    k = max(1, int(round(STEP_S * fps)))
    lhs, rhs = [np.zeros(0)], [np.zeros((0, 2))]
    for f in range(2):
        if len(head) <= k:
            break
        t = np.flatnonzero(np.lib.stride_tricks.sliding_window_view(still[:, f], k + 1).all(axis=1))
        lhs.append((head[t + k] - head[t]).reshape(-1))
        rhs.append(np.stack([-(legs_vec[t + k, f] - legs_vec[t, f]), trunk[t + k] - trunk[t]], -1).reshape(-1, 2))
    return np.concatenate(lhs), np.concatenate(rhs)


def estimate(sig, scale, fps, chest_imu=False, still=None):
    """(legs, equations) from a recording; `still` [T,2] the planted feet when known (else detected)."""
    head, trunk, legs_vec = vectors(sig, scale, chest_imu)
    legs, tau = 1.0, 1.0
    for _ in range(1 if still is not None else 2):
        h, m = equations(head, trunk, legs_vec, still if still is not None else
                         planted(head, trunk, legs_vec, legs, tau, fps), fps)
        if len(h) < 30:
            return np.nan, len(h) // 3
        legs, tau = np.linalg.lstsq(m, h, rcond=None)[0]
    return float(legs), len(h) // 3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--clips", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--chest", action="store_true", help="the chest IMU worn (else the trunk between waist and head)")
    ap.add_argument("--no-noise", action="store_true", help="the IMUs exact (no mounting error, heading drift or jitter)")
    ap.add_argument("--truth-stance", action="store_true", help="the planted feet from the truth (not detected)")
    a = ap.parse_args()
    files = _clips([a.data], "val", a.clips, "unseen")
    worn = LEGS_IMUS + (("chest",) if a.chest else ())
    thigh_shin = np.linalg.norm(OFFSETS[JOINT["l_knee"]]) + np.linalg.norm(OFFSETS[JOINT["l_ankle"]])
    errors = []
    for legs in (0.92, 1.0, 1.08):
        for height in (1.55, 1.75, 1.95):
            body = Body("b", height, legs)
            scale = on_canonical_scale(body)
            est, counts = [], []
            for i, f in enumerate(files):
                take = take_on(load_motion(f, FPS), body, FPS, str(f))
                sig = take.signals if a.no_noise else take_signals(take, worn, index=i, imu_noise=ImuNoise())
                n = min(take.frames, int(a.seconds * FPS))
                still = None
                if a.truth_stance:
                    ankles = take.gt_pos[:n, [JOINT["l_ankle"], JOINT["r_ankle"]]] * scale
                    still = np.linalg.norm(np.gradient(ankles, axis=0), axis=-1) * FPS < 0.1
                e, n = estimate(sig.slice(0, n), scale, FPS, a.chest, still)
                est.append(e)
                counts.append(n)
            err_cm = (np.array(est) - legs) * thigh_shin / scale * 100
            errors.append(err_cm)
            print(f"legs {legs} at {height} m: median estimate {np.nanmedian(est):.3f}; thigh + shin error per clip, "
                  f"cm {np.round(err_cm, 1)}; planted equations per clip {counts}", flush=True)
    e = np.abs(np.concatenate(errors))
    print(f"all bodies and clips: |error| median {np.nanmedian(e):.1f} cm, p90 {np.nanpercentile(e, 90):.1f}, "
          f"within 2 cm {np.mean(e <= 2.0) * 100:.0f} %, clips with no planted stretch {np.isnan(e).sum()}")


if __name__ == "__main__":
    main()
