"""Can the legs' length be had from a user's natural movement? (#54 item 2; the answer measured: no.)

The body keeps the head joint where the stature puts it, so legs `legs` times the canonical body's under a
trunk shorter by what they add leave an upright pose unchanged; only bends and crouches carry `legs`.
With the IMUs' segment directions (waist = pelvis, thighs, shins; the chest, spine and neck guessed between
the waist and the headset, or the chest IMU with `chest`), the head joint's height is linear in `legs`:

    ankle height (flat foot, a0 + legs a1) = head - tau(legs) A + legs B,  tau(legs) = c0 - c1 legs

with A the trunk's and B the lower leg's vertical extent on the canonical offsets. Solved by least squares
over the first minute of each clip, on bodies posed from val's unseen people.

    python bench/legs_from_movement.py [chest]

Prints per body the median estimate and each clip's error in thigh + shin (cm), and the median sensitivity
|den| = |d height / d legs| (m) of each clip.
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from edge import quat
from edge.calibration import devices_on_canonical
from edge.imus import IMU_INDEX
from edge.signals import EYE_OFFSET
from edge.skeleton import HEAD, JOINT, OFFSETS, TOE_HEIGHT, rest_positions
from motion.bodies import Body, take_on
from motion.evaluate import _clips, on_canonical_scale
from motion.retarget import load_motion
from motion.takes import FPS

REST = rest_positions(OFFSETS)
TOE_Y, HEAD_Y = REST[JOINT["l_toe"], 1], REST[HEAD, 1]
C0, C1 = (HEAD_Y - TOE_Y) / HEAD_Y, -TOE_Y / HEAD_Y
A0, A1 = TOE_HEIGHT, REST[JOINT["l_ankle"], 1] - TOE_Y


def up(R, offset):
    return (R @ offset)[..., 1]


def terms(sig, scale, chest_imu):
    """Per frame (num, den) with num = den * legs for the true legs."""
    head_pos, _ = devices_on_canonical(sig.head_pos, sig.head_rot, sig.hand_pos, sig.hand_rot, scale)
    H = head_pos[:, 1] - up(quat.to_matrix(sig.head_rot), EYE_OFFSET)
    pelvis, imu = quat.to_matrix(sig.waist_rot), quat.to_matrix(sig.imu_rot)
    chest_q = sig.imu_rot[:, IMU_INDEX["chest"]] if chest_imu else quat.slerp(sig.waist_rot, sig.head_rot, 0.5)
    spine = quat.to_matrix(quat.slerp(sig.waist_rot, chest_q, 0.5))
    neck = quat.to_matrix(quat.slerp(chest_q, sig.head_rot, 0.5))
    A = (up(pelvis, OFFSETS[JOINT["spine"]]) + up(spine, OFFSETS[JOINT["chest"]])
         + up(quat.to_matrix(chest_q), OFFSETS[JOINT["neck"]]) + up(neck, OFFSETS[JOINT["head"]]))
    B = np.minimum(*[up(pelvis, OFFSETS[JOINT[f"{s}_hip"]]) + up(imu[:, IMU_INDEX[f"{s}_thigh"]], OFFSETS[JOINT[f"{s}_knee"]])
                     + up(imu[:, IMU_INDEX[f"{s}_shin"]], OFFSETS[JOINT[f"{s}_ankle"]]) for s in "lr"])
    return A0 - H + C0 * A, C1 * A + B - A1


def main():
    chest_imu = len(sys.argv) > 1 and sys.argv[1] == "chest"
    files = _clips(["../shared/mocap"], "val", 12, "unseen")
    thigh_shin = np.linalg.norm(OFFSETS[JOINT["l_knee"]]) + np.linalg.norm(OFFSETS[JOINT["l_ankle"]])
    for legs in (0.92, 1.0, 1.08):
        for height in (1.55, 1.95):
            body = Body("b", height, legs)
            scale = on_canonical_scale(body)
            est, sens = [], []
            for f in files:
                take = take_on(load_motion(f, FPS), body, FPS, str(f))
                num, den = terms(take.signals.slice(0, min(take.frames, int(60 * FPS))), scale, chest_imu)
                est.append((num @ den) / (den @ den))
                sens.append(np.median(np.abs(den)))
            err_cm = (np.array(est) - legs) * thigh_shin / scale * 100
            print(f"legs {legs} at {height} m: median estimate {np.median(est):.3f}; |den| per clip "
                  f"{np.round(sens, 3)}; thigh + shin error per clip, cm {np.round(err_cm, 1)}", flush=True)


if __name__ == "__main__":
    main()
