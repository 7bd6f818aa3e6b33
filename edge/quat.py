"""Rotations as plain numpy arrays: quaternions (w, x, y, z), 3x3 matrices and the 6D representation.

Every function is pure and broadcasts over leading dimensions, in the style of orangeduck's quat.h.
"""
import numpy as np


def normalize(q, eps=1e-8):
    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), eps)


def mul(a, b):
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


_CONJUGATE = np.array([1.0, -1.0, -1.0, -1.0])


def inv(q):
    return q * _CONJUGATE.astype(q.dtype, copy=False)


_NEXT, _PREV = np.array([1, 2, 0]), np.array([2, 0, 1])    # index arrays, not lists: no conversion per call


def cross(a, b):
    """Cross product over the last axis (np.cross's axis handling costs more than the arithmetic here)."""
    return a[..., _NEXT] * b[..., _PREV] - a[..., _PREV] * b[..., _NEXT]


def rotate(q, v):
    """Rotate vectors v [...,3] by unit quaternions q [...,4]."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def from_axis_angle(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    angle = np.asarray(angle, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(angle / 2), np.sin(angle / 2) * axis], axis=-1)


_AXES = {"X": np.array([1.0, 0, 0]), "Y": np.array([0, 1.0, 0]), "Z": np.array([0, 0, 1.0])}


def from_euler(angles_deg, order):
    """Intrinsic Euler rotation as BVH writes it: channels 'ZYX' mean R = Rz @ Ry @ Rx."""
    q = None
    for i, axis in enumerate(order):
        qi = from_axis_angle(_AXES[axis], np.radians(angles_deg[..., i]))
        q = qi if q is None else mul(q, qi)
    return q


def to_matrix(q):
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(q.shape[:-1] + (3, 3))


def from_matrix(m):
    """Matrix to quaternion (Shepperd's method, branch per element via masks)."""
    m = np.asarray(m, dtype=np.float64)
    shape = m.shape[:-2]
    m = m.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    q = np.empty((m.shape[0], 4))
    c0 = tr > 0
    c1 = ~c0 & (m[:, 0, 0] > m[:, 1, 1]) & (m[:, 0, 0] > m[:, 2, 2])
    c2 = ~c0 & ~c1 & (m[:, 1, 1] > m[:, 2, 2])
    c3 = ~c0 & ~c1 & ~c2
    s = np.sqrt(np.maximum(tr[c0] + 1.0, 1e-12)) * 2
    q[c0] = np.stack([0.25 * s, (m[c0, 2, 1] - m[c0, 1, 2]) / s, (m[c0, 0, 2] - m[c0, 2, 0]) / s,
                      (m[c0, 1, 0] - m[c0, 0, 1]) / s], -1)
    s = np.sqrt(np.maximum(1.0 + m[c1, 0, 0] - m[c1, 1, 1] - m[c1, 2, 2], 1e-12)) * 2
    q[c1] = np.stack([(m[c1, 2, 1] - m[c1, 1, 2]) / s, 0.25 * s, (m[c1, 0, 1] + m[c1, 1, 0]) / s,
                      (m[c1, 0, 2] + m[c1, 2, 0]) / s], -1)
    s = np.sqrt(np.maximum(1.0 + m[c2, 1, 1] - m[c2, 0, 0] - m[c2, 2, 2], 1e-12)) * 2
    q[c2] = np.stack([(m[c2, 0, 2] - m[c2, 2, 0]) / s, (m[c2, 0, 1] + m[c2, 1, 0]) / s, 0.25 * s,
                      (m[c2, 1, 2] + m[c2, 2, 1]) / s], -1)
    s = np.sqrt(np.maximum(1.0 + m[c3, 2, 2] - m[c3, 0, 0] - m[c3, 1, 1], 1e-12)) * 2
    q[c3] = np.stack([(m[c3, 1, 0] - m[c3, 0, 1]) / s, (m[c3, 0, 2] + m[c3, 2, 0]) / s,
                      (m[c3, 1, 2] + m[c3, 2, 1]) / s, 0.25 * s], -1)
    return normalize(q).reshape(shape + (4,))


def between(u, v):
    """Shortest-arc rotation taking unit vectors u onto unit vectors v."""
    c = np.cross(u, v)
    d = np.sum(u * v, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + d, c], axis=-1)
    # Opposite vectors: rotate by pi about any axis orthogonal to u.
    opposite = (1.0 + d[..., 0]) < 1e-8
    if np.any(opposite):
        ortho = np.cross(u[opposite], np.array([1.0, 0, 0]))
        small = np.linalg.norm(ortho, axis=-1) < 1e-6
        ortho[small] = np.cross(u[opposite][small], np.array([0, 1.0, 0]))
        q[opposite] = np.concatenate([np.zeros((ortho.shape[0], 1)), ortho], axis=-1)
    return normalize(q)


def unroll(q, axis=0):
    """Flip signs along a time axis so consecutive quaternions stay in one hemisphere."""
    q = np.moveaxis(q.copy(), axis, 0)
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    q[1:] *= flips[..., None]
    return np.moveaxis(q, 0, axis)


def slerp(a, b, t):
    t = np.asarray(t, dtype=np.float64)[..., None]
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0, -b, b)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    s = np.sin(theta)
    near = s < 1e-6
    wa = np.where(near, 1.0 - t, np.sin((1.0 - t) * theta) / np.where(near, 1.0, s))
    wb = np.where(near, t, np.sin(t * theta) / np.where(near, 1.0, s))
    return normalize(wa * a + wb * b)


def angle(q):
    """Rotation angle in radians of unit quaternions."""
    return 2.0 * np.arccos(np.clip(np.abs(q[..., 0]), 0.0, 1.0))


def yaw(q):
    """Heading about +Y of the frame's forward axis (+Z), in radians."""
    fwd = rotate(q, _FORWARD)
    return np.arctan2(fwd[..., 0], fwd[..., 2])


_FORWARD, _UP = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])


def from_yaw(theta):
    return from_axis_angle(_UP, theta)


def matrix_to_6d(m):
    """The first two columns of a rotation matrix (Zhou et al. 2019), flattened column-major."""
    return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def matrix_from_6d(r6, out=None):
    """Gram-Schmidt the 6D representation back into a rotation matrix [...,3,3]."""
    a = r6[..., 0:3]
    b = r6[..., 3:6]
    x = a / np.maximum(np.sqrt(np.einsum("...i,...i->...", a, a))[..., None], 1e-8)
    b = b - np.einsum("...i,...i->...", x, b)[..., None] * x
    y = b / np.maximum(np.sqrt(np.einsum("...i,...i->...", b, b))[..., None], 1e-8)
    z = cross(x, y)
    m = np.stack([x, y, z], axis=-1) if out is None else out
    if out is not None:
        out[..., :, 0] = x
        out[..., :, 1] = y
        out[..., :, 2] = z
    return m
