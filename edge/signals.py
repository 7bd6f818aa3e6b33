"""Tracker signals as the board sees them, one frame or a take: the pipeline's input (`Signals`).

motion.synth makes them from a canonical-skeleton motion (training, `edge eval` and the device
simulator all call it); on the board the synchroniser fills them from the devices.
- headset: 6-DoF pose of the eyes (head joint plus an eye offset in the head frame);
- controllers: 6-DoF poses at the grip (wrist plus a grip offset in the wrist frame);
- waist puck: an IMU, so orientation and linear acceleration only (no position);
- extra body IMUs (edge.imus, any subset of seven): each segment's orientation and a presence flag
  (1 worn and fresh, fading to 0 when lost, 0 not worn); `wear` chooses which are worn.
"""
from dataclasses import dataclass, fields

import numpy as np

from edge.imus import NUM_IMUS

EYE_OFFSET = np.array([0.0, 0.09, 0.09])          # head joint -> between the eyes, head frame
GRIP_OFFSET = np.array([[0.07, -0.02, 0.02],      # left wrist -> controller grip, wrist frame
                        [-0.07, -0.02, 0.02]])    # right


@dataclass
class Signals:
    """Tracker signals over T frames (or one frame with T=1). Positions in metres, quaternions (w,x,y,z)."""
    head_pos: np.ndarray    # [T,3] headset
    head_rot: np.ndarray    # [T,4]
    hand_pos: np.ndarray    # [T,2,3] left, right controllers
    hand_rot: np.ndarray    # [T,2,4]
    waist_rot: np.ndarray   # [T,4] puck orientation (IMU fusion output)
    waist_acc: np.ndarray   # [T,3] puck linear acceleration in the sensor frame, m/s^2
    imu_rot: np.ndarray = None    # [T,7,4] extra IMUs' orientations (edge.imus.IMU_LOCATIONS order), held when silent
    imu_flag: np.ndarray = None   # [T,7] their presence, 0..1 (None: none worn)

    def __post_init__(self):
        if self.imu_rot is None:
            self.imu_rot = np.tile(np.array([1.0, 0, 0, 0]), self.head_pos.shape[:-1] + (NUM_IMUS, 1))
        if self.imu_flag is None:
            self.imu_flag = np.zeros(self.head_pos.shape[:-1] + (NUM_IMUS,))

    @property
    def frames(self):
        return self.head_pos.shape[0]

    def slice(self, a, b):
        return Signals(**{f.name: getattr(self, f.name)[a:b] for f in fields(self)})

    def as_dict(self, prefix=""):
        return {prefix + f.name: getattr(self, f.name).astype(np.float32) for f in fields(self)}

    @classmethod
    def from_dict(cls, d, prefix=""):
        """Older recordings carry no extra IMUs: they come back with none worn."""
        return cls(**{f.name: np.asarray(d[prefix + f.name], dtype=np.float64) for f in fields(cls)
                      if prefix + f.name in d})
