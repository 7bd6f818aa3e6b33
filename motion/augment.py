"""One person into another for training: the body mirrored left to right, and the motion at another tempo.

Both act on the canonical motion before anything is synthesised from it, so the headset, controllers and
IMUs of a mirrored or re-timed window are those of the mirrored or re-timed body (not the signals mirrored
after the fact). The canonical skeleton is symmetric (edge.skeleton.OFFSETS: each right bone is its left
bone with x negated), so the mirror is exact: its FK is the reflected FK.
"""
from dataclasses import dataclass

import numpy as np

from edge.imus import IMU_LOCATIONS
from edge.skeleton import JOINT_NAMES


def _swap_sides(names):
    """Index that takes each l_ name to its r_ twin and back; the others stay."""
    twin = {n: ("r_" + n[2:] if n.startswith("l_") else "l_" + n[2:] if n.startswith("r_") else n) for n in names}
    return np.array([names.index(twin[n]) for n in names])


MIRROR_JOINTS = _swap_sides(list(JOINT_NAMES))
MIRROR_IMUS = _swap_sides(list(IMU_LOCATIONS))
# A reflection across the sagittal plane x = 0, S = diag(-1, 1, 1), turns a rotation R into S R S: the
# same angle about the axis (ax, -ay, -az). In quaternions (w, x, y, z): y and z change sign.
_REFLECT_Q = np.array([1.0, 1.0, -1.0, -1.0])
_REFLECT_P = np.array([-1.0, 1.0, 1.0])


def mirror_rotations(rotations):
    """Local joint rotations [..., J, 4] of a body -> those of its mirror image (left and right swapped)."""
    return rotations[..., MIRROR_JOINTS, :] * _REFLECT_Q.astype(rotations.dtype)


def mirror_root(root):
    """Root positions [..., 3] -> reflected across x = 0."""
    return root * _REFLECT_P.astype(root.dtype)


def mirror_contacts(contacts):
    """Foot contacts [..., 2] (left, right) -> (right, left)."""
    return contacts[..., ::-1]


def mirror_imus(mask):
    """A per-IMU array [..., 7] (worn, heard) -> the same IMUs on the other side."""
    return mask[..., MIRROR_IMUS]


@dataclass(frozen=True)
class Augment:
    """What makes one person into another in a training window: a mirror with probability `mirror`,
    and a tempo drawn from [slowest, fastest] (1, 1: none)."""
    mirror: float = 0.0
    slowest: float = 1.0
    fastest: float = 1.0

    @property
    def retimes(self):
        return self.slowest != 1.0 or self.fastest != 1.0

    def draw(self, rng, batch):
        """{"mirror": [B] bool, "speed": [B]} for what is on (nothing when all is off)."""
        d = {}
        if self.mirror > 0:
            d["mirror"] = rng.random(batch) < self.mirror
        if self.retimes:
            d["speed"] = draw_speeds(rng, batch, self.slowest, self.fastest)
        return d


def window_span(window, max_speed):
    """Frames of a clip a window of `window` frames reads at up to max_speed x."""
    return int(np.ceil((window - 1) * max_speed)) + 1


def draw_speeds(rng, batch, low=0.8, high=1.25):
    """A tempo per window, log-uniform in [low, high] so that slower and faster are alike likely."""
    return np.exp(rng.uniform(np.log(low), np.log(high), batch))
