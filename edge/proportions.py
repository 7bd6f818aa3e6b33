"""A user's proportions (#54 item 3): legs long or short for their height, and the pose sent on them.

The model draws the canonical body; the standing calibration brings a user of any height onto it by one
number (edge.calibration). Legs long or short for the height are a second number: `legs`, the leg
bones (hips to toes) against the canonical body's for the same stature, the trunk (pelvis to head)
taking up the difference so the head joint stands where the stature puts it. Adults' legs vary about
4 % either way at one standard deviation for their height (Winter 2009, fig. 4.1).

UserBody puts a pose's joint angles on the user's skeleton, hung from the tracked head as the runtime
hangs the canonical one, in the canonical body's units (the outputs scale to the user's size as
before). A trunk shorter or longer moves the shoulders, and arms longer or shorter (`arms`, the upper
arm and forearm against the canonical body's for the height: the standing calibration measures them
from the controllers held out) reach farther, so each arm is solved again (two-bone IK) to put its
wrist where the pose had it, on the controller, the hand turned as it was.
"""
import ctypes

import numpy as np

from edge import native
from edge.calibration import CANONICAL_ARM
from edge.frame import LIMB_CHAINS, LIMB_POLES, NECK, Pose
from edge.ik import apply_limb_ik
from edge.physics import FLOOR_ANKLE, FLOOR_TOE
from edge.skeleton import ANKLES, HEAD, JOINT, NUM_JOINTS, OFFSETS, PARENTS, TOE_HEIGHT, TOES, fk, rest_positions

LEG_BONES = np.array([JOINT[f"{s}_{j}"] for s in "lr" for j in ("hip", "knee", "ankle", "toe")])
ARM_BONES = np.array([JOINT[f"{s}_{j}"] for s in "lr" for j in ("elbow", "wrist")])
TRUNK_BONES = np.array([JOINT[j] for j in ("spine", "chest", "neck", "head")])
LIMBS_RANGE = (0.8, 1.2)        # five standard deviations either way: anything outside is a measuring error


def proportioned_offsets(legs=1.0, arms=1.0, size=1.0):
    """The canonical skeleton scaled by `size`, its leg bones by `legs` and arm bones by `arms`, the trunk
    bones made shorter or longer so the head joint stands as high as at `size` with canonical legs."""
    rest = rest_positions(OFFSETS)
    off = OFFSETS * size
    off[LEG_BONES] *= legs
    off[ARM_BONES] *= arms
    toe_to_head = (rest[HEAD, 1] - rest[JOINT["l_toe"], 1]) * size
    legs_span = -rest[JOINT["l_toe"], 1] * size * legs               # pelvis down to the toes
    off[TRUNK_BONES] *= (toe_to_head - legs_span) / (rest[HEAD, 1] * size)
    return off


HIP_OVER_TOE = float(rest_positions(OFFSETS)[JOINT["l_hip"], 1] - rest_positions(OFFSETS)[JOINT["l_toe"], 1])
CANONICAL_HIP_HEIGHT = TOE_HEIGHT + HIP_OVER_TOE        # floor to hip joint, standing, the canonical body


def legs_for(leg_length_m, height_scale):
    """`legs` from a leg length measured on the user (floor to the hip joint, standing, m) and the
    calibration's height scale (user -> canonical units)."""
    return (leg_length_m * height_scale - TOE_HEIGHT) / HIP_OVER_TOE


def arms_for(arm_length_m, height_scale):
    """`arms` from an arm measured on the user (shoulder joint to wrist, m; edge.calibration's
    arm_length_from_tpose) and the calibration's height scale."""
    return arm_length_m * height_scale / CANONICAL_ARM


class UserBody:
    """A pose's joint angles on the user's skeleton (`legs`, `arms`), hung from the head joint.
    on_user(pose) -> a Pose of its own (kept, written each frame) with the arms' rotations solved again
    and the positions on the user's skeleton; the canonical body hands the pose back untouched.
    Each frame is one call into the compiled core (edge.native's ep_on_user, nothing allocated) where
    it loads; on_user_numpy is the reference it is tested against, and the fallback."""

    def __init__(self, legs=1.0, arms=1.0, compiled=True):
        for name, v in (("legs", legs), ("arms", arms)):
            if not LIMBS_RANGE[0] <= v <= LIMBS_RANGE[1]:
                raise ValueError(f"{name} {v:g} times the canonical body's for the height: expected "
                                 f"{LIMBS_RANGE[0]:g} to {LIMBS_RANGE[1]:g}")
        self.legs, self.arms = float(legs), float(arms)
        self.canonical = self.legs == 1.0 and self.arms == 1.0
        self.offsets = proportioned_offsets(legs, arms)
        self._world = np.zeros((1, len(OFFSETS), 3, 3))
        self._root = np.zeros((1, 3))
        self._local = np.zeros((1, len(OFFSETS), 3, 3))
        self.pose = Pose(rotations=self._local[0])          # one array each, written in place every frame
        self._ones = np.ones((1, 2))
        self._legs, self._arms = LIMB_CHAINS[:2], LIMB_CHAINS[2:]     # (hip, knee, ankle), (shoulder, elbow, wrist)
        self._leg_poles, self._arm_poles = LIMB_POLES[:2], LIMB_POLES[2:]
        self._lib = native.load() if compiled and not self.canonical else None
        if self._lib is not None:
            self._bind_compiled()

    def _bind_compiled(self):
        """The skeleton and output rows ep_on_user reads and writes, their addresses taken once."""
        chk = native.checked_addr
        self._c = {"parents": np.ascontiguousarray(PARENTS, np.int64), "chains": np.ascontiguousarray(LIMB_CHAINS, np.int64),
                   "ankles": np.ascontiguousarray(ANKLES, np.int64), "offsets": np.ascontiguousarray(self.offsets),
                   "poles": np.ascontiguousarray(LIMB_POLES, np.float64)}
        a = {k: chk(v, v.dtype) for k, v in self._c.items()}
        self._sk = native.Skeleton(J=NUM_JOINTS, head=HEAD, neck=NECK, **a)
        self._rows = native.PoseRows(local=chk(self._local, np.float64, (1, NUM_JOINTS, 3, 3), "user local"),
                                     world=chk(self._world, np.float64, (1, NUM_JOINTS, 3, 3), "user world"),
                                     pos=chk(self.pose.positions, np.float64, (NUM_JOINTS, 3), "user positions"))
        self._sk_ref, self._rows_ref = ctypes.byref(self._sk), ctypes.byref(self._rows)
        self._seen = (None, None, 0, 0)         # the last input arrays and their addresses

    def on_user(self, pose):
        if self.canonical:
            return pose
        if self._lib is None:
            return self.on_user_numpy(pose)
        rot, pos = pose.rotations, pose.positions
        seen = self._seen
        if rot is not seen[0] or pos is not seen[1]:        # a new array: check it once, then only its address
            self._seen = seen = (rot, pos, native.checked_addr(rot, np.float64, (NUM_JOINTS, 3, 3), "pose rotations"),
                                 native.checked_addr(pos, np.float64, (NUM_JOINTS, 3), "pose positions"))
        self._lib.ep_on_user(self._sk_ref, seen[2], seen[3], self._rows_ref)
        return self._finish(pose)

    def _finish(self, pose):
        out = self.pose
        out.contacts = pose.contacts
        out.frame, out.sample, out.transition = pose.frame, pose.sample, pose.transition
        return out

    def on_user_numpy(self, pose):
        """on_user in numpy (the compiled core's reference)."""
        if self.canonical:
            return pose
        out, local, world = self.pose, self._local, self._world
        np.copyto(local[0], pose.rotations)
        pos = out.positions[None]
        fk(local, self._root, offsets=self.offsets, out=(world, pos))
        pos += pose.positions[HEAD] - pos[0, HEAD]
        wrists = self._arms[:, 2]
        hands = world[:, wrists].copy()                 # the hands keep their world orientation
        apply_limb_ik(local, world, pos, PARENTS, self._arms, pose.positions[None, wrists], self._ones,
                      self._arm_poles, end_world_rot=hands, offsets=self.offsets)
        # Longer legs under a shorter trunk reach lower when bent: a foot under the floor (its ankle
        # or toe below the foot IK's floor) is lifted onto it by its leg, as the foot IK would.
        ankles, toes = pos[0, ANKLES], pos[0, TOES]
        lift = np.maximum(np.maximum(FLOOR_ANKLE - ankles[:, 1], FLOOR_TOE - toes[:, 1]), 0.0)
        if lift.any():
            goal = ankles.copy()
            goal[:, 1] += lift
            apply_limb_ik(local, world, pos, PARENTS, self._legs, goal[None], (lift > 0)[None].astype(float),
                          self._leg_poles, offsets=self.offsets)
            # the toes follow their ankles (which kept their world rotation); the wrists end their chains
            pos[0, TOES] = pos[0, ANKLES] + (world[0, ANKLES] @ self.offsets[TOES][..., None])[..., 0]
        return self._finish(pose)
