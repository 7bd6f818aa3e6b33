"""Quaternion helpers (edge.quat) against their definitions: matrices, 6D, Euler order, slerp, between, yaw."""
import numpy as np

from edge import quat


def random_quats(n, seed=0):
    return quat.normalize(np.random.default_rng(seed).standard_normal((n, 4)))


def test_matrix_round_trip_is_identity_up_to_sign():
    q = random_quats(500)
    back = quat.from_matrix(quat.to_matrix(q))
    assert np.allclose(np.abs(np.sum(q * back, -1)), 1.0, atol=1e-9)


def test_rotate_matches_matrix_product():
    q = random_quats(100)
    v = np.random.default_rng(1).standard_normal((100, 3))
    assert np.allclose(quat.rotate(q, v), (quat.to_matrix(q) @ v[..., None])[..., 0])


def test_six_d_round_trip():
    m = quat.to_matrix(random_quats(100))
    assert np.allclose(quat.matrix_from_6d(quat.matrix_to_6d(m)), m, atol=1e-12)


def test_euler_applies_channels_in_listed_order():
    # 'ZYX' means Rz @ Ry @ Rx: rotating x-axis by 90 deg about X leaves it; then Y then Z act on it.
    q = quat.from_euler(np.array([90.0, 0.0, 0.0]), "ZYX")  # Z = 90
    assert np.allclose(quat.rotate(q, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-12)
    q = quat.from_euler(np.array([90.0, 90.0, 0.0]), "ZYX")  # Rz(90) @ Ry(90)
    expected = quat.to_matrix(quat.from_euler(np.array([90.0]), "Z")) @ quat.to_matrix(quat.from_euler(np.array([90.0]), "Y"))
    assert np.allclose(quat.to_matrix(q), expected)


def test_slerp_hits_endpoints_and_halfway_angle():
    a, b = random_quats(50, 1), random_quats(50, 2)
    assert np.allclose(np.abs(np.sum(quat.slerp(a, b, np.zeros(50)) * a, -1)), 1, atol=1e-9)
    assert np.allclose(np.abs(np.sum(quat.slerp(a, b, np.ones(50)) * b, -1)), 1, atol=1e-9)
    mid = quat.slerp(a, b, np.full(50, 0.5))
    d_am = quat.angle(quat.mul(quat.inv(a), mid))
    d_mb = quat.angle(quat.mul(quat.inv(mid), b))
    assert np.allclose(d_am, d_mb, atol=1e-9)


def test_between_maps_u_onto_v_including_opposite_vectors():
    rng = np.random.default_rng(3)
    u = rng.standard_normal((100, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    v = rng.standard_normal((100, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    v[0] = -u[0]
    assert np.allclose(quat.rotate(quat.between(u, v), u), v, atol=1e-9)


def test_yaw_of_from_yaw():
    th = np.linspace(-3, 3, 13)
    assert np.allclose(quat.yaw(quat.from_yaw(th)), th)
