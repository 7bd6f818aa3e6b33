"""Retarget BVH clips from the three source skeletons onto the canonical skeleton.

Each canonical bone takes the world direction of the matching source bone; bone lengths stay
canonical. Joints with one child get the shortest-arc swing from their parent's frame (no twist);
the pelvis and chest, which fan out to several children, get a two-axis frame (hip/shoulder line and
spine). The collars turn about their source's measured mean direction (motion.collars: where each
skeleton puts its collar joint is a convention). The wrists take the source hand's own orientation
against its measured neutral (motion.hands), so synthesised controllers roll and bend like hands, and
the head the source head's turn on the neck
relative to its mean over the clip (`calibrated_head`: the synthesised headset nods and turns on the neck
as a calibrated headset would); the toes keep their parent's orientation. The root translation is scaled by the leg-length ratio and the clip is put on the floor.
"""
from dataclasses import dataclass

import numpy as np

from edge import quat
from motion.bvh import BvhClip, BvhError
from motion.neutrals import collar_neutral_of, hand_neutral_of, neutral_for, normalise_conventions
from edge.skeleton import JOINT, JOINT_NAMES, NUM_JOINTS, OFFSETS, PARENTS, TOE_HEIGHT

_SIDES = ("l", "r")

# Canonical joint -> source joint, per source skeleton.
SOURCE_MAPS = {
    "cmu": {
        "pelvis": "Hips", "spine": "Spine", "chest": "Spine1", "neck": "Neck", "head": "Head",
        **{f"{s}_{k}": f"{S}{v}" for s, S in zip(_SIDES, ("Left", "Right"), strict=True) for k, v in (
            ("collar", "Shoulder"), ("shoulder", "Arm"), ("elbow", "ForeArm"), ("wrist", "Hand"),
            ("hip", "UpLeg"), ("knee", "Leg"), ("ankle", "Foot"), ("toe", "ToeBase"))},
    },
    "daz": {
        "pelvis": "hip", "spine": "abdomen", "chest": "chest", "neck": "neck", "head": "head",
        **{f"{s}_{k}": f"{s}{v}" for s in _SIDES for k, v in (
            ("collar", "Collar"), ("shoulder", "Shldr"), ("elbow", "ForeArm"), ("wrist", "Hand"),
            ("hip", "Thigh"), ("knee", "Shin"), ("ankle", "Foot"), ("toe", "Foot_end"))},
    },
    "bandai": {
        "pelvis": "Hips", "spine": "Spine", "chest": "Chest", "neck": "Neck", "head": "Head",
        **{f"{s}_{k}": f"{v}_{S}" for s, S in zip(_SIDES, ("L", "R"), strict=True) for k, v in (
            ("collar", "Shoulder"), ("shoulder", "UpperArm"), ("elbow", "LowerArm"), ("wrist", "Hand"),
            ("hip", "UpperLeg"), ("knee", "LowerLeg"), ("ankle", "Foot"), ("toe", "Toes"))},
    },
}


def detect_source(clip: BvhClip):
    names = set(clip.names)
    for source, mapping in SOURCE_MAPS.items():
        if all(v in names for v in mapping.values()):
            return source
    raise BvhError(f"{clip.path}: skeleton not recognised (expected CMU, CMU-Daz or Bandai joint names)")


@dataclass
class Motion:
    """A clip on the canonical skeleton: local rotations [T,J,4], root positions [T,3] (metres), fps."""
    rotations: np.ndarray
    root: np.ndarray
    fps: float
    name: str = ""

    @property
    def frames(self):
        return self.rotations.shape[0]


def _frame(primary, secondary):
    """Orthonormal frame [...,3,3] whose first column is primary and second lies in the primary/secondary plane."""
    a = primary / np.linalg.norm(primary, axis=-1, keepdims=True)
    b = secondary - np.sum(secondary * a, axis=-1, keepdims=True) * a
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.stack([a, b, np.cross(a, b)], axis=-1)


# Two-axis frames for joints that fan out: (primary vector, secondary vector) as joint-name pairs.
_FAN_FRAMES = {
    "pelvis": (("r_hip", "l_hip"), ("pelvis", "spine")),
    "chest": (("chest", "neck"), ("r_shoulder", "l_shoulder")),
}


def calibrated_head(neck_world, head_world):
    """The head's world rotation [T,4] as a calibrated headset reads it: the source head's own turn on the
    neck, relative to its mean over the clip. A mocap head bone sits on each performer differently (a
    median sideways tilt of 25 deg on some of data v4's Daz performers, 10 on others); a headset
    calibrated in a T-pose reads level when its wearer looks ahead. What is left is the head's motion on
    the neck: nodding and turning, p50 15 deg, p95 43 on val's unseen people."""
    local = quat.mul(quat.inv(neck_world), head_world)
    local = np.where((local @ local[0])[:, None] < 0, -local, local)
    mean = quat.normalize(local.mean(0))
    return quat.normalize(quat.mul(neck_world, quat.mul(local, quat.inv(mean)[None])))


def _about_neutral(d, parent_world, mean_dir, rest_dir):
    """World directions d [T,3] turned, in the parent's frame, by the swing that takes the source's mean
    direction there to the canonical rest direction (motion.collars)."""
    swing = quat.between(np.asarray(mean_dir, dtype=np.float64), rest_dir)
    local = quat.rotate(quat.inv(parent_world), d)
    return quat.rotate(parent_world, quat.rotate(np.broadcast_to(swing, parent_world.shape), local))


def retarget(clip: BvhClip, source=None, unit=0.01, hands=True, collars=True, conventions=True):
    """Source clip -> canonical Motion, plus the source joint world positions [T,J,3] (metres) it followed.
    hands=False gives the wrists their forearm's orientation and the head its neck's (what motion.hands
    measures against); collars=False the collars their source's direction as it is (what motion.collars
    measures against); conventions=False the pelvis, spine, chest, neck and feet their source's
    convention as it is (what motion.conventions measures against; motion.neutrals)."""
    source = source or detect_source(clip)
    neutral = hand_neutral_of(clip.path, source) if hands else None
    collar_mean = collar_neutral_of(clip.path, source) if collars else None
    mapping = SOURCE_MAPS[source]
    _, src_world = clip.world()
    src = np.stack([src_world[:, clip.index(mapping[n])] for n in JOINT_NAMES], axis=1) * unit
    T = clip.frames
    rest = np.zeros((NUM_JOINTS, 3))
    for j in range(1, NUM_JOINTS):
        rest[j] = rest[PARENTS[j]] + OFFSETS[j]

    children = {j: np.flatnonzero(PARENTS == j) for j in range(NUM_JOINTS)}
    world = np.zeros((T, NUM_JOINTS, 4))
    local = np.zeros((T, NUM_JOINTS, 4))
    for j, name in enumerate(JOINT_NAMES):
        parent_world = world[:, PARENTS[j]] if j > 0 else np.tile([1.0, 0, 0, 0], (T, 1))
        if name in _FAN_FRAMES:
            (a0, a1), (b0, b1) = _FAN_FRAMES[name]
            f_src = _frame(src[:, JOINT[a1]] - src[:, JOINT[a0]], src[:, JOINT[b1]] - src[:, JOINT[b0]])
            f_rest = _frame(rest[JOINT[a1]] - rest[JOINT[a0]], rest[JOINT[b1]] - rest[JOINT[b0]])
            world[:, j] = quat.from_matrix(f_src @ f_rest.T)
        elif len(children[j]) == 1:
            c = children[j][0]
            d = src[:, c] - src[:, j]
            d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
            rest_dir = OFFSETS[c] / np.linalg.norm(OFFSETS[c])
            if collar_mean is not None and name in ("l_collar", "r_collar"):
                d = _about_neutral(d, parent_world, collar_mean[name[0]], rest_dir)
            u = quat.rotate(parent_world, np.broadcast_to(rest_dir, (T, 3)))
            world[:, j] = quat.normalize(quat.mul(quat.between(u, d), parent_world))
        elif neutral is not None and name in ("l_wrist", "r_wrist"):
            world[:, j] = quat.normalize(quat.mul(hand_world(clip, source, name[0]), np.asarray(neutral[name[0]])))
        elif hands and name == "head":
            world[:, j] = calibrated_head(parent_world, head_world(clip, source))
        else:  # leaf: keep the parent's orientation
            world[:, j] = parent_world
        local[:, j] = quat.mul(quat.inv(parent_world), world[:, j]) if j > 0 else world[:, j]

    # Root translation: scale by leg length so stride matches the canonical legs.
    def leg(p):
        return np.linalg.norm(p[:, JOINT["l_knee"]] - p[:, JOINT["l_hip"]], axis=-1) + \
            np.linalg.norm(p[:, JOINT["l_ankle"]] - p[:, JOINT["l_knee"]], axis=-1)
    scale = (np.linalg.norm(OFFSETS[JOINT["l_knee"]]) + np.linalg.norm(OFFSETS[JOINT["l_ankle"]])) / np.median(leg(src))
    root = src[:, 0] * scale
    local = quat.normalize(local)
    if conventions:         # before the floor: a foot's convention sets how high its ankle stands
        local, _ = normalise_conventions(local, neutral_for(clip.path))
    motion = Motion(quat.unroll(local), root, clip.fps, clip.path)
    place_on_floor(motion)
    return motion, src


def place_on_floor(motion: Motion):
    """Shift the clip vertically so the lower toe's 5th-percentile height is the rest toe height."""
    from edge.skeleton import fk
    _, pos = fk(quat.to_matrix(motion.rotations), motion.root)
    lowest = np.min(pos[:, [JOINT["l_toe"], JOINT["r_toe"]], 1], axis=1)
    motion.root[:, 1] += TOE_HEIGHT - np.percentile(lowest, 5)


def direction_errors_deg(motion: Motion, src):
    """Angle between each canonical bone and its source bone, [T, J-1] degrees (bone = joint j minus its parent)."""
    from edge.skeleton import fk
    _, pos = fk(quat.to_matrix(motion.rotations), motion.root)
    j = np.arange(1, NUM_JOINTS)
    a = pos[:, j] - pos[:, PARENTS[j]]
    b = src[:, j] - src[:, PARENTS[j]]
    cos = np.sum(a * b, -1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


LIMB_BONES = np.array([JOINT[f"{s}_{k}"] for s in _SIDES for k in ("elbow", "wrist", "knee", "ankle", "toe")]) - 1


def frames_at(rotations, root, t):
    """The motion at fractional frame positions t [...] (indices into rotations [F,J,4], root [F,3]):
    slerp for rotations, linear for the root. -> (rotations, root). resample reads every clip through
    it, and training's tempo augmentation (motion.augment) its windows."""
    t = np.asarray(t, dtype=np.float64)
    i0 = np.minimum(np.floor(t).astype(int), len(root) - 1)
    i1 = np.minimum(i0 + 1, len(root) - 1)
    w = t - i0
    rot = quat.slerp(rotations[i0], rotations[i1], np.broadcast_to(w[..., None], w.shape + (rotations.shape[-2],)))
    return rot, root[i0] * (1 - w[..., None]) + root[i1] * w[..., None]


def resample(motion: Motion, fps=60.0):
    """Resample to a new rate: slerp for rotations, linear for the root."""
    if abs(motion.fps - fps) < 1e-3:
        return Motion(motion.rotations, motion.root, fps, motion.name)
    duration = (motion.frames - 1) / motion.fps
    rot, root = frames_at(motion.rotations, motion.root, np.arange(0.0, duration + 1e-9, 1.0 / fps) * motion.fps)
    return Motion(quat.unroll(rot), root, fps, motion.name)


def load_motion(path, fps=60.0, conventions=True):
    """BVH file -> canonical Motion at the model rate (conventions=False: each source's skeleton
    conventions left in, motion.neutrals)."""
    from motion import bvh
    motion, _ = retarget(bvh.load(path), conventions=conventions)
    return resample(motion, fps)


def head_world(clip, source):
    """The source head's world rotation [T,4]."""
    world_rot, _ = clip.world()
    return world_rot[:, clip.index(SOURCE_MAPS[source]["head"])]


def hand_world(clip, source, side):
    """The source hand's world rotation [T,4] of one side ("l" or "r")."""
    world_rot, _ = clip.world()
    return world_rot[:, clip.index(SOURCE_MAPS[source][f"{side}_wrist"])]
