"""Extra body IMUs (DragPoser's variable sensor sets): where a user can wear them, which skeleton
segment each one measures, the sets people wear, how a tracker's presence flag fades when it is
lost and returns, and the device noise of a real IMU after a T-pose calibration.

One place for this: training, `edge eval`, the simulator and the synchroniser use the same names,
the same fade and the same noise, so the model sees at run time what it was trained on.
"""
from dataclasses import dataclass

import numpy as np

from edge import quat
from edge.skeleton import JOINT

# Each location measures the segment that starts at this joint (l_thigh is l_hip's segment, ...).
IMU_SEGMENTS = {"chest": "chest", "l_thigh": "l_hip", "r_thigh": "r_hip", "l_shin": "l_knee",
                "r_shin": "r_knee", "l_foot": "l_ankle", "r_foot": "r_ankle"}
IMU_LOCATIONS = tuple(IMU_SEGMENTS)
NUM_IMUS = len(IMU_LOCATIONS)
IMU_JOINTS = np.array([JOINT[j] for j in IMU_SEGMENTS.values()])
IMU_INDEX = {name: i for i, name in enumerate(IMU_LOCATIONS)}
# Every body location a config may give an IMU tracker: the waist (always worn) and the extra seven.
TRACKER_NAMES = ("waist",) + IMU_LOCATIONS
# The sets people commonly wear beyond the waist (SlimeVR's usual kits; DragPoser Tables 1-2 compare such sets).
COMMON_SETS = (
    ("l_shin", "r_shin"),
    ("l_thigh", "r_thigh", "l_shin", "r_shin"),
    ("chest", "l_thigh", "r_thigh", "l_shin", "r_shin"),
    IMU_LOCATIONS,
    ("l_foot", "r_foot"),
)
# The synchroniser's timing, in seconds: a tracker silent for LOST_AFTER_S is lost; its flag then fades
# to 0 over FADE_S, and back to 1 over FADE_S when it returns.
LOST_AFTER_S = 0.25
FADE_S = 0.25


def parse_set(text):
    """'none' / '' -> (), 'all' -> the seven, 'l_shin,r_shin' -> ('l_shin', 'r_shin'). ValueError names the valid ones."""
    text = (text or "").strip()
    if text in ("", "none"):
        return ()
    if text == "all":
        return IMU_LOCATIONS
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in IMU_INDEX]
    if bad:
        raise ValueError(f"unknown tracker location(s) {', '.join(bad)}: valid are {', '.join(IMU_LOCATIONS)} "
                         f"(or 'none', 'all')")
    return tuple(sorted(set(names), key=IMU_INDEX.get))


def mask(names):
    """Tracker names -> presence [7] (1 worn, 0 not)."""
    m = np.zeros(NUM_IMUS)
    m[[IMU_INDEX[n] for n in names]] = 1.0
    return m


def fade(alive, fps, held=None, lost_after_s=LOST_AFTER_S, fade_s=FADE_S):
    """What the synchroniser makes of trackers that go silent and come back.

    alive [T,...,K] bool (a fresh sample arrived that frame); held [T,...,K,4] the orientations.
    Returns (flags [T,...,K] in 0..1, held orientations [T,...,K,4] or None). A silent tracker keeps its
    last orientation; after lost_after_s it is lost and its flag falls linearly to 0 over fade_s; when it
    returns, the fresh orientation is used at once and the flag climbs back over fade_s."""
    T = alive.shape[0]
    lost_n, step = int(round(lost_after_s * fps)), 1.0 / max(1.0, fade_s * fps)
    flags = np.empty(alive.shape)
    flag = alive[0].astype(float)
    since = np.where(alive[0], 0, lost_n + 1)
    out = None if held is None else held.copy()
    for t in range(T):
        a = alive[t]
        since = np.where(a, 0, since + 1)
        target = (since < lost_n).astype(float) if t else a.astype(float)
        flag = np.clip(flag + np.clip(target - flag, -step, step), 0.0, 1.0) if t else flag
        flags[t] = flag
        if out is not None and t:
            out[t] = np.where(a[..., None], held[t], out[t - 1])
    return flags, out


def dragposer_drops(rng, T, worn, fps=60.0, p=0.01, frames=100):
    """DragPoser's faulty-sensor protocol: each frame, one worn tracker drops with probability p and
    returns after `frames` frames. worn [K] mask -> alive [T,K] bool."""
    alive = np.repeat(worn[None] > 0, T, axis=0)
    idx = np.flatnonzero(worn > 0)
    if len(idx) == 0:
        return alive
    for t in np.flatnonzero(rng.random(T) < p):
        k = rng.choice(idx)
        alive[t:t + frames, k] = False
    return alive


def axis_angle_deg(axis, deg):
    """Axes [...,3] (any length) and angles in degrees [...] -> quaternions [...,4] (the noise models'
    random rotations, from their drawn axes and angles)."""
    return quat.from_axis_angle(axis / np.linalg.norm(axis, axis=-1, keepdims=True), np.radians(deg))


@dataclass
class ImuNoise:
    """A body IMU after calibration (LoBSTR's sensor noise; DragPoser's noisy sensors): a mounting error
    of a few degrees that the T-pose leaves (fixed, in the segment's frame), a heading offset that
    drifts (gyro integration, about the vertical), and per-sample jitter."""
    mount_max_deg: float = 5.0
    yaw_offset_std_deg: float = 3.0
    yaw_drift_deg_s: float = 0.5
    jitter_max_deg: float = 1.0

    def draw(self, rng, shape):
        """The random numbers of one application to orientations of `shape` ([T,...,K]), as a dict
        (models.batches draws the same on a device)."""
        rest = shape[1:]
        return {"mount_axis": rng.standard_normal(rest + (3,)), "mount_deg": rng.uniform(0, self.mount_max_deg, rest),
                "yaw_offset_deg": rng.normal(0, self.yaw_offset_std_deg, rest),
                "yaw_drift_deg_s": rng.normal(0, self.yaw_drift_deg_s, rest),
                "jitter_axis": rng.standard_normal(shape + (3,)), "jitter_deg": rng.uniform(0, self.jitter_max_deg, shape)}

    def apply(self, rot, fps, rng):
        """rot [T,...,K,4] world orientations -> the same, as the IMUs report them."""
        return self.apply_drawn(rot, fps, self.draw(rng, rot.shape[:-1]))

    def apply_drawn(self, rot, fps, d):
        T, rest = rot.shape[0], rot.shape[1:-1]
        mount = axis_angle_deg(d["mount_axis"], d["mount_deg"])
        t = (np.arange(T) / fps).reshape((T,) + (1,) * len(rest))
        yaw = np.radians(d["yaw_offset_deg"] + d["yaw_drift_deg_s"] * t)
        jitter = axis_angle_deg(d["jitter_axis"], d["jitter_deg"])
        return quat.normalize(quat.mul(quat.from_yaw(yaw), quat.mul(jitter, quat.mul(rot, mount[None]))))
