"""SE(3) helpers: inverses, exp/log round trips, quaternions, interpolation and averaging."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvtop_cli.geometry import se3


def random_poses(rng, n, t_scale=0.1):
    R = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    return se3.make_pose(R, rng.normal(0, t_scale, (n, 3)))


def test_invert_composes_to_identity():
    T = random_poses(np.random.default_rng(0), 50)
    np.testing.assert_allclose(T @ se3.invert(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_exp_log_round_trip_including_small_angles():
    rng = np.random.default_rng(1)
    xi = np.concatenate([rng.normal(0, 0.05, (200, 3)), rng.normal(0, 1.0, (200, 3))], axis=1)
    norms = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / norms)  # log returns the principal branch, |w| < pi
    xi[:20, 3:] *= 1e-9  # series expansion branch
    np.testing.assert_allclose(se3.log_se3(se3.exp_se3(xi)), xi, atol=1e-9)


def test_exp_matches_matrix_exponential():
    from scipy.linalg import expm

    rng = np.random.default_rng(2)
    for xi in rng.normal(0, 0.5, (10, 6)):
        M = np.zeros((4, 4))
        w = xi[3:]
        M[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        M[:3, 3] = xi[:3]
        np.testing.assert_allclose(se3.exp_se3(xi), expm(M), atol=1e-12)


def test_quaternion_round_trip_and_convention():
    T = random_poses(np.random.default_rng(3), 30)
    q = se3.to_quat_xyzw(T)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(se3.from_quat_xyzw(q, T[:, :3, 3]), T, atol=1e-12)
    # 90 deg about z: (x, y, z, w) = (0, 0, sin 45, cos 45)
    Tz = se3.make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.zeros(3))
    np.testing.assert_allclose(se3.to_quat_xyzw(Tz), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)


def test_transform_points_batched_equals_loop():
    rng = np.random.default_rng(4)
    T = random_poses(rng, 5)
    p = rng.normal(size=(7, 3))
    batched = se3.transform_points(T, p)
    for i in range(5):
        np.testing.assert_allclose(batched[i], (T[i][:3, :3] @ p.T).T + T[i][:3, 3], atol=1e-12)


def test_interpolate_midpoint():
    T0 = se3.make_pose(np.eye(3), [0, 0, 0])
    T1 = se3.make_pose(Rotation.from_euler("x", 60, degrees=True).as_matrix(), [0.2, 0, 0])
    Tm = se3.interpolate(T0, T1, 0.5)
    assert np.degrees(se3.rotation_angle(Tm[:3, :3])) == pytest.approx(30.0)
    np.testing.assert_allclose(Tm[:3, 3], [0.1, 0, 0])


def test_weighted_mean_is_a_rotation_average_not_a_matrix_average():
    # +-80 deg about z: the matrix average is not a rotation; the mean must be the identity.
    a = se3.make_pose(Rotation.from_euler("z", 80, degrees=True).as_matrix(), [0.001, 0, 0])
    b = se3.make_pose(Rotation.from_euler("z", -80, degrees=True).as_matrix(), [-0.001, 0, 0])
    m = se3.weighted_mean(np.stack([a, b]))
    np.testing.assert_allclose(m, np.eye(4), atol=1e-12)
    # weights pull towards the heavier pose
    m2 = se3.weighted_mean(np.stack([a, b]), np.array([3.0, 1.0]))
    assert m2[0, 3] == pytest.approx(0.0005)
    assert 0 < np.degrees(se3.rotation_angle(m2[:3, :3])) < 80


def test_pose_spread_matches_sample_statistics():
    rng = np.random.default_rng(5)
    base = random_poses(rng, 1)[0]
    n = 20000
    dt = rng.normal(0, 0.001, (n, 3))
    dw = rng.normal(0, np.radians(0.5), (n, 3))
    T = se3.make_pose(se3.rotvec_to_matrix(dw), dt) @ base
    T[:, :3, 3] = base[:3, 3] + dt
    mean, cov = se3.pose_spread(T)
    np.testing.assert_allclose(np.sqrt(np.diag(cov))[:3], 0.001, rtol=0.03)
    np.testing.assert_allclose(np.sqrt(np.diag(cov))[3:], np.radians(0.5), rtol=0.03)
    assert np.degrees(se3.rotation_angle(mean[:3, :3], base[:3, :3])) < 0.05
