"""Bodies that are not the canonical one (issue #54): a stature and leg and arm lengths for it, the
skeleton they make, and a recording posed on it with its devices synthesised from that body.

A body is the canonical skeleton with its legs (hips to toes) and arms (upper arm and forearm) made
longer or shorter by a factor, then scaled whole to the stature asked for, so "long legs" means long
for the person's height, as anthropometry states it. Proportions, as shares of stature, follow
Winter, "Biomechanics and Motor Control of Human Movement" (4th ed., 2009, fig. 4.1, after Drillis
and Contini 1966): eye height 0.936 H. Adult legs and arms vary about 4 % either way at one standard
deviation for their height (the spread the issue cites); the standard set goes to two (8 %).
"""
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge import quat
from edge.calibration import EYE_TO_STATURE          # Winter (2009) fig. 4.1
from edge.signals import EYE_OFFSET
from edge.imus import IMU_LOCATIONS
from edge.proportions import ARM_BONES, LEG_BONES, TRUNK_BONES, proportioned_offsets  # noqa: F401  (bench reads them here)
from edge.skeleton import HEAD, JOINT, OFFSETS, TOE_HEIGHT, fk, rest_positions
from motion.synth import synthesize_from_pose
from motion.takes import Take


def eye_height(offsets):
    """The eyes' height above the floor standing in the rest pose, on the skeleton `offsets`."""
    rest = rest_positions(offsets)
    return TOE_HEIGHT - rest[JOINT["l_toe"], 1] + rest[HEAD, 1] + EYE_OFFSET[1]


CANONICAL_STATURE = eye_height(OFFSETS) / EYE_TO_STATURE


@dataclass(frozen=True)
class Body:
    name: str
    height_m: float                 # stature
    legs: float = 1.0               # leg length against the canonical body's, for the same stature
    arms: float = 1.0

    def size(self):
        """The factor the canonical skeleton is scaled by to this stature (average proportions)."""
        rest = rest_positions(OFFSETS)
        span = rest[HEAD, 1] - rest[JOINT["l_toe"], 1]       # toe to head joint; the eyes' offset is the headset's
        return (EYE_TO_STATURE * self.height_m - TOE_HEIGHT - EYE_OFFSET[1]) / span

    def offsets(self):
        """The body's skeleton: each joint's offset from its parent (m), as edge.skeleton.OFFSETS. Legs
        long for the stature leave the trunk (pelvis to head) shorter, so the eyes stay where the
        stature puts them; arms hang off it and change nothing else."""
        return proportioned_offsets(self.legs, self.arms, self.size())

    def leg_scale(self):
        """How much longer than the canonical body's the legs are (hips to toes, the same for each bone)."""
        return self.legs * self.size()

    def to_json(self):
        return {"name": self.name, "height_m": self.height_m, "legs": self.legs, "arms": self.arms}


CANONICAL = Body("canonical", float(CANONICAL_STATURE))


def standard_bodies():
    """The canonical body, three statures by three leg lengths (short, average, long for the height: two
    standard deviations), and long and short arms at the middle stature."""
    out = [CANONICAL]
    for h in (1.55, 1.75, 1.95):
        for legs, say in ((0.92, "short legs"), (1.0, ""), (1.08, "long legs")):
            out.append(Body(f"{h:.2f} m" + (f", {say}" if say else ""), h, legs))
    out += [Body("1.75 m, short arms", 1.75, arms=0.92), Body("1.75 m, long arms", 1.75, arms=1.08)]
    return out


def load_bodies(spec):
    """'standard', or a JSON file: a list of {name, height_m, legs?, arms?}. ValueError says what is wrong."""
    if spec == "standard":
        return standard_bodies()
    try:
        rows = json.loads(Path(spec).read_text())
        bodies = [Body(str(r["name"]), float(r["height_m"]), float(r.get("legs", 1.0)), float(r.get("arms", 1.0)))
                  for r in rows]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"--bodies {spec}: not 'standard' or a JSON list of {{name, height_m, legs, arms}} ({e})") from None
    for b in bodies:
        if not (1.0 <= b.height_m <= 2.3 and 0.7 <= b.legs <= 1.3 and 0.7 <= b.arms <= 1.3):
            raise ValueError(f"--bodies {spec}: {b.name!r} is outside 1.0-2.3 m or limbs 0.7-1.3x")
    if not any(b.name == "canonical" for b in bodies):
        bodies.insert(0, CANONICAL)             # the figures are read against it
    return bodies


def take_on(motion, body, fps, name):
    """A canonical Motion (local rotations, root) posed on `body`: the same joint angles, the root's
    path scaled with the pelvis' height (the feet stay on the floor, steps as long as the legs), the
    devices synthesised from that body. Its truth is the body's FK. Everything from the pelvis down
    is the canonical body's times leg_scale, so a foot on the floor there is on the floor here."""
    offsets = body.offsets()
    root = motion.root * body.leg_scale()
    world_rot_m, pos = fk(quat.to_matrix(motion.rotations), root, offsets=offsets)
    sig = synthesize_from_pose(world_rot_m, pos, fps)
    return Take(name, sig, pos, fps, {n: sig.imu_rot[:, k] for k, n in enumerate(IMU_LOCATIONS)})


def measured_limbs(body, rng, hold_frames=60, tremor_m=0.005):
    """What the board measures of `body` in `edge calibrate` (#54 item 2): the arms from the controllers
    held out in the T-pose (edge.calibration.arm_length_from_tpose) and the legs from the left controller
    held at the side of the hip (leg_length_from_hip), each hold `hold_frames` long with `tremor_m` of
    hand tremor, the devices synthesised on the body standing on the floor. Returns (legs, arms) as
    UserBody takes them and the largest error of the two limb lengths (cm). The hand's placement on the
    bony point is taken as exact: the error a person adds there is theirs, not the measurement's."""
    from edge.calibration import arm_length_from_tpose, height_scale_for, leg_length_from_hip
    from edge.proportions import arms_for, legs_for
    from edge.signals import GRIP_OFFSET
    off = body.offsets()
    rest = rest_positions(off)
    rest[:, 1] += TOE_HEIGHT * body.leg_scale() - rest[JOINT["l_toe"], 1]       # standing on the floor
    eye = eye_height(off)
    scale = height_scale_for(eye)
    wrists = rest[[JOINT["l_wrist"], JOINT["r_wrist"]]]
    hand_rot = np.tile([1.0, 0, 0, 0], (hold_frames, 2, 1))
    held_out = wrists + GRIP_OFFSET + rng.normal(0, tremor_m, (hold_frames, 2, 3))
    arm = arm_length_from_tpose(held_out, hand_rot, np.ones((hold_frames, 2), bool), scale)
    at_hip = np.zeros((hold_frames, 2, 3))
    at_hip[:, 0] = rest[JOINT["l_hip"]] + [0.1, 0.0, 0.0] + rng.normal(0, tremor_m, (hold_frames, 3))
    at_hip[:, 1] = rest[JOINT["r_wrist"]] * [1, 0, 1] + [0, 0.8 * rest[JOINT["l_hip"], 1], 0]    # the other hanging
    leg = leg_length_from_hip(at_hip, np.ones((hold_frames, 2), bool), eye)
    true_arm = float(np.linalg.norm(off[JOINT["l_elbow"]]) + np.linalg.norm(off[JOINT["l_wrist"]]))
    true_leg = float(rest[JOINT["l_hip"], 1])
    error_cm = 100 * max(abs(arm - true_arm), abs(leg - true_leg))
    return legs_for(leg, scale), arms_for(arm, scale), error_cm
