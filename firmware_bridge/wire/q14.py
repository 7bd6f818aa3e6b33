"""The Q14 quaternion codec every wire format here uses: w, x, y, z as int16 with 1.0 = 16384.

The serial messages (messages.py), the CAN tracker frames (can_frames.py) and the BNO055's output
registers (transports/bno055.py, datasheet Table 3-31) all carry unit quaternions this way. A decoded
quaternion whose norm is further than NORM_TOLERANCE from 1 is not a rotation but a damaged
transfer; Q14 rounding alone moves the norm by less than 1e-4.
"""
import numpy as np

SCALE = 16384
INT16_MAX = 32767
NORM_TOLERANCE = 0.02


def to_q14(q):
    """Quaternions [..., 4] -> int16 counts [..., 4], normalised first. ValueError on NaN, infinity or zero."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(norm < 1e-6):
        raise ValueError("cannot encode a quaternion that is NaN, infinite or zero")
    return np.clip(np.round(q / norm * SCALE), -INT16_MAX, INT16_MAX).astype("<i2")


def from_q14(counts):
    """int16 counts [..., 4] -> quaternions as sent (not renormalised)."""
    return np.asarray(counts, dtype=np.float64) / SCALE


def to_bytes(q):
    """One quaternion [4] -> its 8 bytes, int16 little-endian (a CAN frame's or the BNO055's layout)."""
    return to_q14(q).tobytes()


def from_bytes(data):
    """8 bytes, int16 little-endian -> [4] quaternion as sent."""
    return from_q14(np.frombuffer(bytes(data), dtype="<i2"))


def norm_error(q):
    """|norm - 1| per quaternion [...] (inf where not finite)."""
    n = np.linalg.norm(np.asarray(q, dtype=np.float64), axis=-1)
    return np.where(np.isfinite(n), np.abs(n - 1.0), np.inf)


def is_unit(q, tolerance=NORM_TOLERANCE):
    """True where a decoded quaternion is a rotation: finite and unit length within `tolerance`."""
    return norm_error(q) <= tolerance
