"""Plain sample objects every transport yields (python-can's Message is the model: data, no behaviour).

Conventions shared with `edge`: metres, Y-up, quaternions (w, x, y, z), seconds.
"""
from dataclasses import dataclass, field

import numpy as np


@dataclass
class TrackerSample:
    """One IMU tracker reading (serial hub, I2C BNO055 or CAN node)."""
    tracker: str                     # which tracker, e.g. "waist", "l_foot" (config maps ids to names)
    t: float                         # device timestamp, seconds, in the device's own clock
    quat: np.ndarray                 # [4] fused orientation (w, x, y, z), unit
    accel: np.ndarray = None         # [3] linear acceleration in the sensor frame, m/s^2 (None if not sent)
    status: int = 0                  # device status / calibration bits, transport specific
    received: float = 0.0            # host time.monotonic() at reception


@dataclass
class HeadsetSample:
    """One headset report: head and controller 6-DoF poses."""
    t: float                         # headset timestamp, seconds, headset clock
    head_pos: np.ndarray             # [3]
    head_rot: np.ndarray             # [4]
    hand_pos: np.ndarray             # [2,3] left, right
    hand_rot: np.ndarray             # [2,4]
    hand_valid: np.ndarray = field(default_factory=lambda: np.ones(2, bool))  # controller tracked?
    received: float = 0.0


@dataclass
class TargetSample:
    """A point the headset asks a joint to reach (edge.refine): within `radius` metres, over a window of
    `duration` seconds starting `start` seconds after the board receives it; `clear` removes target
    `target_id` instead. Values are as sent: the board checks them before any is applied."""
    t: float                         # headset timestamp, seconds, headset clock
    target_id: int
    joint: int                       # edge.skeleton joint index (protocol.md section 5's order)
    position: np.ndarray             # [3] world (the headset's tracking space), metres
    radius: float
    start: float
    duration: float
    clear: bool = False
    received: float = 0.0
