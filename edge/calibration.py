"""Standing calibration: IMU mounting offsets and the user's height scale (LoBSTR 4.2, SSI 4.4).

The user stands upright in a T-pose (arms out, facing forward) for a few seconds. From that:
- height scale: canonical eye height / measured headset height. The model works on the canonical
  body, so tracker positions are multiplied by it (around the floor origin) and poses divided back.
- the headset's mounting rotation (how it sits on the face: pitched or rolled against a level head), so
  that it reads level, facing where it faces, while the user looks ahead. The synthesised headsets
  training and `val` see read that way (motion.retarget.calibrated_head), and the head joint is placed
  from the headset along it.
- per IMU tracker, a heading alignment A (yaw only: the IMU's magnetic/gyro heading reference against
  the headset's) and a mounting rotation M (how the sensor sits on the body), so that
  body orientation = A * sensor * M, and in the calibration pose every body part is upright facing
  where the headset faces (the canonical rest pose has identity rotations).
Limitation: a tracker mounted with a yaw twist folds that twist into A, which is exact for turning
but slightly off for leaning; a second pose (a bow) would separate them.
"""
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from edge import quat
from edge.shutdown import replace_whole
from edge.signals import EYE_OFFSET, GRIP_OFFSET, Signals
from edge.skeleton import JOINT, OFFSETS, PELVIS_HEIGHT, PELVIS_TO_HEAD

CANONICAL_EYE_HEIGHT = PELVIS_HEIGHT + PELVIS_TO_HEAD[1] + EYE_OFFSET[1]
EYE_TO_STATURE = 0.936              # eye height standing over stature (Winter 2009, fig. 4.1)
# 2: the eye height measured is kept, and the height scale is the head joint's (what v1 files said is
# converted on load: their scale was the eyes').
VERSION = 2
# The canonical shoulders' span (shoulder joint to shoulder joint) and arm (shoulder joint to wrist).
SHOULDER_SPAN = 2 * (OFFSETS[JOINT["l_collar"], 0] + OFFSETS[JOINT["l_shoulder"], 0])
CANONICAL_ARM = float(np.linalg.norm(OFFSETS[JOINT["l_elbow"]]) + np.linalg.norm(OFFSETS[JOINT["l_wrist"]]))


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message says what to do."""


def mean_quat(q):
    """Average of nearby unit quaternions [K,4] (sign-aligned mean, renormalised)."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where((q @ q[0])[:, None] < 0, -q, q)
    return quat.normalize(q.mean(0))


@dataclass
class Calibration:
    height_scale: float = 1.0
    heading: float = 0.0                                  # headset yaw during calibration, radians
    eye_height_m: float = None                            # the headset's height standing, as measured
    arm_length_m: float = None                            # shoulder to wrist, from the T-pose's controllers
    leg_length_m: float = None                            # floor to hip joint, a controller held at the hip
    align: dict = field(default_factory=dict)             # tracker -> [4] yaw alignment A
    mount: dict = field(default_factory=dict)             # tracker -> [4] mounting rotation M

    def body_rotation(self, tracker, sensor_q):
        """Sensor orientation(s) [...,4] -> body-part orientation A * q * M (identity if uncalibrated)."""
        if tracker not in self.mount:
            return sensor_q
        return quat.mul(quat.mul(self.align[tracker], sensor_q), self.mount[tracker])

    def to_json(self):
        return {"version": VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
                "height_scale": self.height_scale,
                "eye_height_m": self.eye_height_m or eye_height_for(self.height_scale),
                "arm_length_m": self.arm_length_m, "leg_length_m": self.leg_length_m,
                "stature_m": self.stature_m(), "heading_deg": float(np.degrees(self.heading)),
                "trackers": {k: {"align": self.align[k].tolist(), "mount": self.mount[k].tolist()} for k in self.mount}}

    def stature_m(self):
        """The user's height, from the headset's standing (eyes at EYE_TO_STATURE of it)."""
        eye = self.eye_height_m if self.eye_height_m else eye_height_for(self.height_scale)
        return eye / EYE_TO_STATURE

    def with_stature(self, stature_m):
        """This calibration for a user `stature_m` tall (a height written in the config wins over the
        one measured)."""
        eye = EYE_TO_STATURE * stature_m
        return Calibration(height_scale_for(eye), self.heading, eye, self.arm_length_m, self.leg_length_m, self.align,
                           self.mount)

    def save(self, path):
        """Write the calibration whole: a stop or a crash mid-write leaves the previous file (edge.shutdown)."""
        with replace_whole(path) as tmp:
            tmp.write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def load(cls, path):
        try:
            d = json.loads(Path(path).read_text())
            if d.get("version") not in (1, VERSION):
                raise CalibrationError(f"{path}: calibration version {d.get('version')} is not {VERSION}; run edge calibrate again")
            scale = float(d["height_scale"])
            if not 0.5 < scale < 2.0:
                raise CalibrationError(f"{path}: height scale {scale:.3f} is implausible; run edge calibrate again")
            # v1 kept the eyes' ratio only: the eye height it measured, and the head joint's ratio from it
            eye = float(d["eye_height_m"]) if d.get("eye_height_m") else CANONICAL_EYE_HEIGHT / scale
            if not 0.8 < eye < 2.3:
                raise CalibrationError(f"{path}: eye height {eye:.2f} m is implausible; run edge calibrate again")
            cal = cls(height_scale_for(eye), np.radians(float(d.get("heading_deg", 0.0))), eye)
            if d.get("arm_length_m") is not None:
                cal.arm_length_m = float(d["arm_length_m"])
                if not 0.3 < cal.arm_length_m < 0.9:
                    raise CalibrationError(f"{path}: arm length {cal.arm_length_m:.2f} m is implausible; run edge calibrate again")
            if d.get("leg_length_m") is not None:
                cal.leg_length_m = float(d["leg_length_m"])
                if not 0.5 < cal.leg_length_m < 1.4:
                    raise CalibrationError(f"{path}: leg length {cal.leg_length_m:.2f} m is implausible; run edge calibrate again")
            for name, t in d.get("trackers", {}).items():
                a, m = np.array(t["align"], dtype=np.float64), np.array(t["mount"], dtype=np.float64)
                if a.shape != (4,) or m.shape != (4,) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(m))):
                    raise CalibrationError(f"{path}: tracker {name!r} has a malformed rotation; run edge calibrate again")
                cal.align[name], cal.mount[name] = quat.normalize(a), quat.normalize(m)
            return cal
        except FileNotFoundError:
            raise CalibrationError(f"calibration file {path} not found: run `edge calibrate --config ...` first, "
                                   f"or leave `calibration` out of the config to run uncalibrated") from None
        except (ValueError, KeyError, TypeError) as e:
            if isinstance(e, CalibrationError):
                raise
            raise CalibrationError(f"{path}: not a valid calibration file ({e}); run edge calibrate again") from None


def height_scale_for(eye_height_m):
    """The canonical body's size over the user's, from the headset's height standing (LoBSTR 4.2:
    positions scaled to the training body). The head joint's heights, not the eyes': the eyes sit a
    headset's offset in front of and above the joint whatever the size of the person."""
    return (CANONICAL_EYE_HEIGHT - EYE_OFFSET[1]) / (eye_height_m - EYE_OFFSET[1])


def eye_height_for(height_scale):
    """The headset's standing height a height scale was measured from (height_scale_for's inverse)."""
    return (CANONICAL_EYE_HEIGHT - EYE_OFFSET[1]) / height_scale + EYE_OFFSET[1]


def devices_on_canonical(head_pos, head_rot, hand_pos, hand_rot, scale):
    """The headset's and controllers' positions [...,3] from the user's body onto the canonical one,
    around the floor origin: (head_pos, hand_pos). The body is scaled, the devices are not: the head
    and wrist joints move by `scale`, the eyes and grips keep their offsets from them (scaling the grip
    with the body put a 1.55 m user's wrists 1.2 cm off the controllers)."""
    if scale == 1.0:
        return head_pos, hand_pos
    keep = 1.0 - scale
    return (head_pos * scale + keep * quat.rotate(head_rot, EYE_OFFSET),
            hand_pos * scale + keep * quat.rotate(hand_rot, GRIP_OFFSET))


def product_matrix(a, m):
    """The 4x4 matrix T with T q = a * q * m for every quaternion q [4] (the product is linear in q)."""
    return np.stack([quat.mul(quat.mul(a, e), m) for e in np.eye(4)], axis=-1)


def rotation_forms(v):
    """Q [...,3,4,4] with rotate(q, v)_i = q . Q[..., i] q for every unit quaternion q: the rotation of
    fixed vectors v [...,3] as three quadratic forms each, from R(q) v = (w^2 - u.u) v + 2 (u.v) u +
    2 w (u x v), which is homogeneous of degree two (polarised on the basis)."""
    v = np.asarray(v, float)

    def rotated(q):
        w, u = q[0], q[1:]
        return (w * w - u @ u) * v + 2.0 * (v @ u)[..., None] * u + 2.0 * w * np.cross(u, v)

    e = np.eye(4)
    Q = np.zeros(v.shape[:-1] + (3, 4, 4))
    for j in range(4):
        for k in range(4):
            Q[..., j, k] = rotated(e[j]) if j == k else 0.5 * (rotated(e[j] + e[k]) - rotated(e[j]) - rotated(e[k]))
    return Q


class FrameCalibration:
    """A Calibration applied to each frame of Signals on the way in: the user scaled onto the canonical
    body (around the floor origin), the headset levelled (q M), the waist and each worn extra IMU turned
    from its sensor frame onto its body segment (A q M).

    Per frame it makes no arrays: A q M is a fixed 4x4 matrix on q (product_matrix), the eye and grip
    offsets turned by a device's orientation are fixed quadratic forms (rotation_forms), and the result
    is written into one Signals (T=1) kept for the next frame, so a caller uses it before the next call."""

    def __init__(self, calibration, imus=()):
        """imus: (tracker name, slot in Signals.imu_rot) of each worn extra IMU."""
        from edge.imus import NUM_IMUS
        cal = self.calibration = calibration
        identity = np.array([1.0, 0.0, 0.0, 0.0])
        self.scale, self.keep = float(cal.height_scale), 1.0 - float(cal.height_scale)

        def turn(tracker):          # q -> A q M, as q @ T' (identity where the tracker is not calibrated)
            if tracker not in cal.mount:
                return np.eye(4)
            return product_matrix(cal.align.get(tracker, identity), cal.mount[tracker]).T

        self.head_turn, self.waist_turn = turn("head"), turn("waist")
        # The extra IMUs' [7,4] as one [28] row: a block-diagonal [28,28] (identity where none is worn).
        self.imu_turn = np.eye(4 * NUM_IMUS)
        for name, k in imus:
            self.imu_turn[4 * k:4 * k + 4, 4 * k:4 * k + 4] = turn(name)
        self.eye_forms = rotation_forms(EYE_OFFSET).reshape(12, 4)               # [3*4, 4]
        self.grip_forms = rotation_forms(GRIP_OFFSET).reshape(2, 12, 4)          # per controller
        self.out = Signals(np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 2, 3)), np.zeros((1, 2, 4)),
                           np.zeros((1, 4)), np.zeros((1, 3)), np.zeros((1, NUM_IMUS, 4)), np.zeros((1, NUM_IMUS)))
        self._imu_in = np.zeros(4 * NUM_IMUS)
        self._imu_out = self.out.imu_rot.reshape(-1)                    # a view: written in place
        self._eye_q, self._eye_off = np.zeros((3, 4)), np.zeros(3)
        self._grip_q, self._grip_off = np.zeros((2, 3, 4)), np.zeros((2, 3))

    def __call__(self, sig):
        """The calibrated frame of sig (Signals, T=1), in self.out. np.dot with out= throughout: it makes
        no temporaries (np.matmul and einsum do, a few hundred bytes to a few KB a call)."""
        o, keep = self.out, self.keep
        np.dot(sig.head_rot, self.head_turn, out=o.head_rot)
        np.dot(sig.waist_rot, self.waist_turn, out=o.waist_rot)
        np.copyto(self._imu_in, sig.imu_rot.reshape(-1))
        np.dot(self._imu_in, self.imu_turn, out=self._imu_out)
        np.copyto(o.hand_rot, sig.hand_rot)
        np.copyto(o.waist_acc, sig.waist_acc)
        np.copyto(o.imu_flag, sig.imu_flag)
        # devices_on_canonical: the head and wrists scaled, the eyes' and grips' offsets from them kept
        np.multiply(sig.head_pos, self.scale, out=o.head_pos)
        np.multiply(sig.hand_pos, self.scale, out=o.hand_pos)
        if keep != 0.0:
            head_q = o.head_rot[0]
            np.dot(self.eye_forms, head_q, out=self._eye_q.reshape(12))
            np.dot(self._eye_q, head_q, out=self._eye_off)
            self._eye_off *= keep
            o.head_pos[0] += self._eye_off
            for h in (0, 1):                    # the two controllers
                hand_q = sig.hand_rot[0, h]
                np.dot(self.grip_forms[h], hand_q, out=self._grip_q[h].reshape(12))
                np.dot(self._grip_q[h], hand_q, out=self._grip_off[h])
            self._grip_off *= keep
            o.hand_pos[0] += self._grip_off
        return o


def calibrate(head_pos, head_rot, trackers):
    """head_pos [K,3], head_rot [K,4] over the standing period; trackers: name -> sensor quats [K,4]."""
    head_pos, head_rot = np.asarray(head_pos), np.asarray(head_rot)
    height = float(np.median(head_pos[:, 1]))
    if height < 0.8:
        raise CalibrationError(f"headset only {height:.2f} m above the floor: stand upright during calibration "
                               f"(and check the headset's floor level)")
    heading = float(quat.yaw(mean_quat(head_rot)))
    cal = Calibration(height_scale_for(height), heading, height)
    face = quat.from_yaw(np.array(heading))
    # the headset is the heading reference (no A); its M levels it: head_rot * M is the face in the T-pose
    cal.align["head"] = np.array([1.0, 0.0, 0.0, 0.0])
    cal.mount["head"] = quat.normalize(quat.mul(quat.inv(mean_quat(head_rot)), face))
    for name, q in trackers.items():
        s = mean_quat(q)
        a = quat.from_yaw(np.array(heading - quat.yaw(s)))
        cal.align[name] = a
        cal.mount[name] = quat.normalize(quat.mul(quat.inv(quat.mul(a, s)), face))
    return cal


def leg_length_from_hip(hand_pos, hand_valid, eye_height_m):
    """The user's leg (floor to the hip joint, m) from the left controller held against the bony point at
    the side of the left hip (the greater trochanter, at the hip joint's height), standing: its median
    height over the hold, [K,2,3] and [K,2]. (The left one, named: a hanging hand is lower than the
    hip, so "the lower controller" would pick the wrong one.) As good as the hold: the error is how far
    the hand sits above or below the bony point. CalibrationError says what to do when it cannot be made
    (#54 item 2)."""
    hand_pos, valid = np.asarray(hand_pos, float), np.asarray(hand_valid, bool)
    held = valid[:, 0]
    if held.mean() < 0.8:
        raise CalibrationError("the left controller was not tracked for most of the hold: keep it in view")
    y = hand_pos[held, 0, 1]
    spread = float(np.percentile(y, 90) - np.percentile(y, 10))
    leg = float(np.median(y))
    if spread > 0.03:
        raise CalibrationError(f"the left controller moved {100 * spread:.0f} cm up and down: hold it still "
                               "against the bony point at the side of the left hip")
    if not 0.40 < leg / eye_height_m < 0.65:
        raise CalibrationError(f"the left controller was {leg:.2f} m up with the eyes at {eye_height_m:.2f} m: hold "
                               "it against the bony point at the side of the left hip, standing upright")
    return leg


def arm_length_from_tpose(hand_pos, hand_rot, hand_valid, height_scale):
    """The user's arm (shoulder joint to wrist, m) from the controllers held out in the T-pose
    [K,2,3], [K,2,4], [K,2]: half the wrists' span less the shoulders' (the canonical span at the user's
    size). CalibrationError says what to do when it cannot be made (#54 item 2)."""
    tracked = np.asarray(hand_valid, bool).all(axis=1)
    if tracked.mean() < 0.8:
        raise CalibrationError("a controller was not tracked for most of the T-pose: keep both in view")
    wrists = hand_pos[tracked] - quat.rotate(hand_rot[tracked], GRIP_OFFSET)
    span = float(np.median(np.linalg.norm(wrists[:, 0] - wrists[:, 1], axis=-1)))
    level = float(np.median(np.abs(wrists[:, 0, 1] - wrists[:, 1, 1])))
    arm = (span - SHOULDER_SPAN / height_scale) / 2
    if level > 0.10 or not 0.75 < arm * height_scale / CANONICAL_ARM < 1.3:
        raise CalibrationError(f"the arms were not straight out to the sides (wrists {span:.2f} m apart, "
                               f"{100 * level:.0f} cm apart in height): stand in a T-pose, arms level")
    return arm
