"""The canonical skeleton every source is retargeted onto, and forward kinematics on it.

Rest pose is a T-pose in metres, Y-up, facing +Z, the character's left at +X. Every joint's
rest local rotation is the identity, so a joint's local rotation is its rotation away from
the T-pose. Bone lengths are fixed (a ~1.75 m adult); users are scaled to it at calibration.
"""
import numpy as np

JOINT_NAMES = (
    "pelvis", "spine", "chest", "neck", "head",
    "l_collar", "l_shoulder", "l_elbow", "l_wrist",
    "r_collar", "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle", "l_toe",
    "r_hip", "r_knee", "r_ankle", "r_toe",
)
PARENTS = np.array([-1, 0, 1, 2, 3, 2, 5, 6, 7, 2, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19])
JOINT = {name: i for i, name in enumerate(JOINT_NAMES)}
NUM_JOINTS = len(JOINT_NAMES)

# Offset of each joint from its parent in the rest pose (metres).
OFFSETS = np.array([
    [0.00, 0.00, 0.00],    # pelvis (root)
    [0.00, 0.11, 0.00],    # spine
    [0.00, 0.20, 0.00],    # chest
    [0.00, 0.22, 0.00],    # neck
    [0.00, 0.10, 0.00],    # head (base of skull)
    [0.03, 0.17, 0.00],    # l_collar
    [0.14, 0.00, 0.00],    # l_shoulder
    [0.28, 0.00, 0.00],    # l_elbow
    [0.25, 0.00, 0.00],    # l_wrist
    [-0.03, 0.17, 0.00],   # r_collar
    [-0.14, 0.00, 0.00],   # r_shoulder
    [-0.28, 0.00, 0.00],   # r_elbow
    [-0.25, 0.00, 0.00],   # r_wrist
    [0.09, -0.06, 0.00],   # l_hip
    [0.00, -0.43, 0.00],   # l_knee
    [0.00, -0.42, 0.00],   # l_ankle
    [0.00, -0.07, 0.13],   # l_toe
    [-0.09, -0.06, 0.00],  # r_hip
    [0.00, -0.43, 0.00],   # r_knee
    [0.00, -0.42, 0.00],   # r_ankle
    [0.00, -0.07, 0.13],   # r_toe
])

# Joints the network predicts a rotation for (all but the root, whose rotation is the waist IMU's).
PREDICTED = np.arange(1, NUM_JOINTS)
NUM_PREDICTED = len(PREDICTED)
# Lower body: what SSI's plausibility score averages over (SSI 3.2.1).
LOWER_BODY = np.array([JOINT[n] for n in ("l_hip", "l_knee", "l_ankle", "l_toe",
                                          "r_hip", "r_knee", "r_ankle", "r_toe")])
FEET = np.array([JOINT["l_toe"], JOINT["r_toe"]])
ANKLES = np.array([JOINT["l_ankle"], JOINT["r_ankle"]])
HEAD = JOINT["head"]
TOES = FEET
# The two legs as (hip, knee, ankle, toe) rows: lower-body FK runs both legs at once.
LEGS = np.array([[JOINT[f"{s}_{k}"] for k in ("hip", "knee", "ankle", "toe")] for s in "lr"])
WRISTS = np.array([JOINT["l_wrist"], JOINT["r_wrist"]])

# Joints grouped by depth, so FK runs one batched step per level instead of one per joint.
def _depths(parents):
    d = np.zeros(len(parents), dtype=int)
    for j in range(1, len(parents)):
        d[j] = d[parents[j]] + 1
    return d


DEPTH = _depths(PARENTS)
LEVELS = tuple(np.flatnonzero(DEPTH == k) for k in range(1, DEPTH.max() + 1))


def rest_positions(offsets=OFFSETS):
    """World joint positions of the rest pose with the pelvis at the origin."""
    p = np.zeros((len(offsets), 3))
    for j in range(1, len(offsets)):
        p[j] = p[PARENTS[j]] + offsets[j]
    return p


REST = rest_positions()
# Pelvis-to-head vector in the rest pose: used to place the waist under the headset.
PELVIS_TO_HEAD = REST[HEAD] - REST[0]
# Height of the toes and ankles above the floor when standing in the rest pose.
TOE_HEIGHT = 0.02
PELVIS_HEIGHT = TOE_HEIGHT - REST[JOINT["l_toe"], 1]


def fk(local_rot, root_pos, offsets=OFFSETS, out=None):
    """Forward kinematics. local_rot [...,J,3,3], root_pos [...,3] -> (world_rot [...,J,3,3], world_pos [...,J,3]).

    `out` = (world_rot, world_pos) arrays to fill instead of allocating.
    """
    if out is None:
        world_rot = np.empty_like(local_rot)
        world_pos = np.empty(local_rot.shape[:-2] + (3,), dtype=local_rot.dtype)
    else:
        world_rot, world_pos = out
    world_rot[..., 0, :, :] = local_rot[..., 0, :, :]
    world_pos[..., 0, :] = root_pos
    for idx in LEVELS:
        par = PARENTS[idx]
        world_rot[..., idx, :, :] = world_rot[..., par, :, :] @ local_rot[..., idx, :, :]
        world_pos[..., idx, :] = world_pos[..., par, :] + (world_rot[..., par, :, :] @ offsets[idx][..., None])[..., 0]
    return world_rot, world_pos


def fk_legs(pelvis_rot, pelvis_pos, leg_local, offsets=OFFSETS):
    """Positions of both legs only. pelvis_rot [B,3,3], pelvis_pos [B,3], leg_local [B,2,3,3,3]
    (hip, knee, ankle local rotations per leg) -> [B,2,4,3] (hip, knee, ankle, toe)."""
    off = offsets[LEGS]                                               # [2,4,3]
    pos = np.empty(leg_local.shape[:2] + (4, 3))
    rot = pelvis_rot[:, None]                                         # [B,1,3,3]
    base = pelvis_pos[:, None]
    for k in range(4):
        base = base + (rot @ off[:, k, :, None])[..., 0]
        pos[:, :, k] = base
        if k < 3:
            rot = rot @ leg_local[:, :, k]
    return pos
