"""Pose metrics: hand-computed values on small cases, symmetries, batched == looped."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvtop_cli.config import load_config
from mvtop_cli.eval import metrics as M
from mvtop_cli.geometry import se3

REPO = Path(__file__).resolve().parents[2]
CUBE = M.box_corners((-0.0125, -0.0125, 0.0), (0.0125, 0.0125, 0.025))  # configs/meshes/cube.obj [m]


def rot(axis: str, deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    return se3.make_pose(Rotation.from_euler(axis, deg, degrees=True).as_matrix(), np.asarray(t, dtype=float))


def random_poses(rng: np.random.Generator, n: int, t_scale: float = 0.05) -> np.ndarray:
    R = Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()
    return se3.make_pose(R, rng.normal(0, t_scale, (n, 3)))


@pytest.fixture(scope="module")
def cube_group() -> np.ndarray:
    cfg = load_config(REPO / "configs" / "cube.yaml")
    return M.symmetry_group(np.stack([s.matrix() for s in cfg.object.symmetries]))


def test_one_millimetre_translation_is_one_millimetre_everywhere(cube_group):
    rng = np.random.default_rng(3)
    T_gt = random_poses(rng, 1)[0]
    d = rng.normal(size=3)
    d *= 1e-3 / np.linalg.norm(d)
    T_est = se3.make_pose(T_gt[:3, :3], T_gt[:3, 3] + d)  # shifted 1 mm in the world
    for value in (
        M.translation_error(T_est, T_gt),
        M.pose_error_bbox(T_est, T_gt, CUBE),
        M.add(T_est, T_gt, CUBE),
        M.adi(T_est, T_gt, CUBE),  # corners are 25 mm apart: the nearest is the own corner
        M.mssd(T_est, T_gt, CUBE),
        M.mssd(T_est, T_gt, CUBE, cube_group),
        M.add(T_est, T_gt, CUBE, cube_group),
    ):
        assert float(value) == pytest.approx(1e-3, abs=1e-12)
    assert float(M.rotation_error(T_est, T_gt)) == pytest.approx(0.0, abs=1e-7)


def test_lateral_displacement_ignores_the_insertion_axis():
    T_gt = se3.make_pose(np.eye(3), (0.1, 0.2, 0.3))
    along = se3.make_pose(np.eye(3), (0.1, 0.2, 0.3 + 0.002))  # 2 mm along the object z axis
    across = se3.make_pose(np.eye(3), (0.1 + 0.0003, 0.2 + 0.0004, 0.3))  # 0.5 mm across it
    assert float(M.lateral_displacement(along, T_gt, CUBE)) == pytest.approx(0.0, abs=1e-15)
    assert float(M.lateral_displacement(across, T_gt, CUBE)) == pytest.approx(5e-4, abs=1e-15)
    # The axis is the truth's: tilt the truth and the same world offset is lateral.
    tilted = rot("x", 90.0, (0.1, 0.2, 0.3))
    assert float(
        M.lateral_displacement(tilted @ se3.make_pose(np.eye(3), (0, 0, 0.002)), tilted, CUBE)
    ) == pytest.approx(0, abs=1e-15)
    # A yaw of theta moves a corner at radius r by the chord 2 r sin(theta / 2).
    r = 0.0125 * math.sqrt(2)
    assert float(M.lateral_displacement(T_gt @ rot("z", 2.0), T_gt, CUBE)) == pytest.approx(
        2 * r * math.sin(math.radians(1.0)), rel=1e-12)


def test_cube_quarter_turn_is_zero_with_symmetries_but_not_for_add(cube_group):
    assert len(cube_group) == 24  # 23 listed in the config, plus the identity
    T_gt = random_poses(np.random.default_rng(5), 1)[0]
    T_est = T_gt @ rot("z", 90.0)  # the origin is on the z axis (centre of the bottom face)
    assert float(M.adi(T_est, T_gt, CUBE)) == pytest.approx(0.0, abs=1e-12)
    assert float(M.add(T_est, T_gt, CUBE, cube_group)) == pytest.approx(0.0, abs=1e-12)
    assert float(M.mssd(T_est, T_gt, CUBE, cube_group)) == pytest.approx(0.0, abs=1e-12)
    assert float(M.pose_error_bbox(T_est, T_gt, CUBE, cube_group)) == pytest.approx(0.0, abs=1e-12)
    k = int(M.closest_symmetry(T_est, T_gt, CUBE, cube_group))
    assert float(M.rotation_error(T_est @ cube_group[k], T_gt)) == pytest.approx(0.0, abs=1e-7)
    assert float(M.translation_error(T_est @ cube_group[k], T_gt)) == pytest.approx(0.0, abs=1e-12)
    # Without symmetries every corner moves by the chord 2 r sin(45 deg) = 25 mm.
    assert float(M.add(T_est, T_gt, CUBE)) == pytest.approx(0.025, rel=1e-12)
    assert float(M.mssd(T_est, T_gt, CUBE)) == pytest.approx(0.025, rel=1e-12)
    assert float(M.rotation_error(T_est, T_gt)) == pytest.approx(math.pi / 2, rel=1e-12)
    # A flip onto the top face (180 deg about x through the cube's centre) is a symmetry too.
    flip = rot("x", 180.0, (0.0, 0.0, 0.025))
    assert float(M.mssd(T_gt @ flip, T_gt, CUBE, cube_group)) == pytest.approx(0.0, abs=1e-12)
    assert float(M.mssd(T_gt @ flip, T_gt, CUBE)) == pytest.approx(math.sqrt(0.025**2 + 0.025**2), rel=1e-12)


def test_mssd_of_a_known_rotation_of_a_box():
    half = np.array([0.01, 0.005, 0.02])
    box = M.box_corners(-half, half)
    T_gt = random_poses(np.random.default_rng(7), 1)[0]
    # 30 deg about x: a corner at distance rho from the axis moves 2 rho sin(15 deg).
    rho = math.hypot(0.005, 0.02)
    assert float(M.mssd(T_gt @ rot("x", 30.0), T_gt, box)) == pytest.approx(
        2 * rho * math.sin(math.radians(15)), rel=1e-12
    )
    # The box's symmetries (180 deg about each axis): a half turn about z costs nothing...
    syms = np.stack([rot(a, 180.0) for a in "xyz"])
    assert float(M.mssd(T_gt @ rot("z", 180.0), T_gt, box, syms)) == pytest.approx(0.0, abs=1e-12)
    assert float(M.mssd(T_gt @ rot("z", 180.0), T_gt, box)) == pytest.approx(2 * math.hypot(0.01, 0.005), rel=1e-12)
    # ...and a 10 deg turn about z is nearest to the identity: 2 rho_z sin(5 deg).
    assert float(M.mssd(T_gt @ rot("z", 10.0), T_gt, box, syms)) == pytest.approx(
        2 * math.hypot(0.01, 0.005) * math.sin(math.radians(5)), rel=1e-12)


def test_bbox_pose_error_is_the_mean_corner_distance():
    box = M.box_corners((0, 0, 0), (0.02, 0.01, 0.0))  # a flat 20 x 10 mm plate in z = 0
    # A quarter turn about z through the origin: corners at radius 0, 10, 20, sqrt(500) mm
    # (each twice) move by sqrt(2) times their radius.
    expected = math.sqrt(2) * (0 + 0.01 + 0.02 + math.hypot(0.02, 0.01)) / 4
    assert float(M.pose_error_bbox(rot("z", 90.0), np.eye(4), box)) == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(M.bbox_corners(box), box)


def test_batched_equals_looped(cube_group):
    rng = np.random.default_rng(11)
    T_gt = random_poses(rng, 40)
    T_est = T_gt @ se3.exp_se3(rng.normal(0, [0.002] * 3 + [0.2] * 3, (40, 6)))
    pts = rng.normal(0, 0.01, (50, 3))
    funcs = {
        "translation": lambda a, b: M.translation_error(a, b),
        "rotation": lambda a, b: M.rotation_error(a, b),
        "tangent": lambda a, b: M.tangent_error(a, b),
        "add": lambda a, b: M.add(a, b, pts),
        "add_sym": lambda a, b: M.add(a, b, pts, cube_group),
        "adi": lambda a, b: M.adi(a, b, pts),
        "mssd": lambda a, b: M.mssd(a, b, pts, cube_group),
        "bbox": lambda a, b: M.pose_error_bbox(a, b, CUBE, cube_group),
        "lateral": lambda a, b: M.lateral_displacement(a, b, CUBE, (0, 0, 1), cube_group),
        "closest": lambda a, b: M.closest_symmetry(a, b, CUBE, cube_group),
    }
    for name, f in funcs.items():
        batched = f(T_est, T_gt)
        looped = np.stack([f(a, b) for a, b in zip(T_est, T_gt)])
        np.testing.assert_allclose(batched, looped, rtol=1e-12, atol=1e-15, err_msg=name)
    # One truth against many estimates broadcasts.
    np.testing.assert_allclose(M.mssd(T_est, T_gt[0], pts), [M.mssd(a, T_gt[0], pts) for a in T_est], rtol=1e-12)
    # Chunking: force tiny chunks, same values.
    big = M.mssd(T_est, T_gt, pts, cube_group)
    old = M._CHUNK_ELEMENTS
    M._CHUNK_ELEMENTS = 1
    try:
        np.testing.assert_allclose(M.mssd(T_est, T_gt, pts, cube_group), big, rtol=1e-12)
    finally:
        M._CHUNK_ELEMENTS = old


def test_ground_truth_scores_zero(cube_group):
    T = random_poses(np.random.default_rng(13), 20)
    for v in (M.translation_error(T, T), M.rotation_error(T, T), M.add(T, T, CUBE), M.adi(T, T, CUBE),
              M.mssd(T, T, CUBE, cube_group), M.lateral_displacement(T, T, CUBE)):
        np.testing.assert_allclose(v, 0.0, atol=1e-7)
    np.testing.assert_array_equal(M.closest_symmetry(T, T, CUBE, cube_group), 0)


def test_symmetry_group_closes_generators_and_rejects_non_symmetries():
    g = M.symmetry_group(rot("z", 90.0)[None])
    assert len(g) == 4
    np.testing.assert_allclose(g[0], np.eye(4))
    assert len(M.symmetry_group(None)) == 1
    assert len(M.symmetry_group(np.stack([rot("z", 90.0), rot("x", 90.0)]))) == 24
    with pytest.raises(ValueError, match="finite group"):
        M.symmetry_group(rot("z", math.degrees(1.0))[None], max_size=50)


def test_nees_and_chi2_bound_hand_values():
    sigma = np.array([1e-3, 2e-3, 1e-3, 0.01, 0.02, 0.01])
    e = np.array([1e-3, 1e-3, 0.0, 0.02, 0.0, -0.01])
    # (1)^2 + (0.5)^2 + 0 + (2)^2 + 0 + (1)^2 = 6.25
    assert float(M.nees(e, np.diag(sigma**2))) == pytest.approx(6.25, rel=1e-12)
    assert M.chi2_bound(6, 0.95) == pytest.approx(12.5916, abs=1e-4)
    assert M.chi2_bound(3, 0.95) == pytest.approx(7.8147, abs=1e-4)
    P = np.array([[2.0, 1.0], [1.0, 2.0]])
    assert float(M.nees([1.0, 1.0], P)) == pytest.approx(2 / 3, rel=1e-12)  # P^-1 = [[2,-1],[-1,2]]/3


def test_tangent_error_is_the_left_perturbation():
    rng = np.random.default_rng(17)
    T_est = random_poses(rng, 1)[0]
    dt, dw = np.array([1e-3, -2e-3, 5e-4]), np.array([0.01, -0.02, 0.03])
    T_gt = se3.make_pose(se3.rotvec_to_matrix(dw) @ T_est[:3, :3], T_est[:3, 3] + dt)
    np.testing.assert_allclose(M.tangent_error(T_est, T_gt), np.r_[dt, dw], atol=1e-12)


def test_shift_covariance_matches_samples_moved_by_a_symmetry():
    rng = np.random.default_rng(19)
    T = random_poses(rng, 1)[0]
    S = rot("x", 180.0, (0.0, 0.0, 0.025))  # the cube's flip, a long lever arm
    cov = np.diag([1e-7, 2e-7, 5e-8, 1e-5, 4e-6, 9e-6])
    d = rng.multivariate_normal(np.zeros(6), cov, 200_000)
    samples = se3.make_pose(se3.rotvec_to_matrix(d[:, 3:]) @ T[:3, :3], T[:3, 3] + d[:, :3])
    _, cov_moved = se3.pose_spread(samples @ S)
    predicted = M.shift_covariance(cov, T, S)
    assert not np.allclose(predicted, cov)  # the lever arm matters...
    # ...as predicted: whitened by the prediction, the sample covariance is the identity
    # up to sampling noise (~sqrt(2 / n) = 0.003) and the first-order approximation.
    W = np.linalg.inv(np.linalg.cholesky(predicted))
    np.testing.assert_allclose(W @ cov_moved @ W.T, np.eye(6), atol=0.02)
    Wc = np.linalg.inv(np.linalg.cholesky(cov))
    assert np.abs(Wc @ cov_moved @ Wc.T - np.eye(6)).max() > 0.1  # the unshifted one is not


def test_clipped_bounds_of_a_pyramid():
    # Square pyramid: base 20 x 20 mm at z = 0, apex at z = 10 mm. Cut at 5 mm: 10 x 10 mm.
    v = np.array([[-0.01, -0.01, 0], [0.01, -0.01, 0], [0.01, 0.01, 0], [-0.01, 0.01, 0], [0, 0, 0.01]])
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [0, 4], [1, 4], [2, 4], [3, 4]])
    lo, hi = M.clipped_bounds(v, edges, 0.005)
    np.testing.assert_allclose(lo, [-0.01, -0.01, 0.0], atol=1e-15)
    np.testing.assert_allclose(hi, [0.01, 0.01, 0.005], atol=1e-15)
    # The same pyramid upside down (apex at z = 0): the cut is 10 x 10 mm.
    v2 = v.copy()
    v2[:, 2] = 0.01 - v2[:, 2]
    lo, hi = M.clipped_bounds(v2, edges, 0.005)
    np.testing.assert_allclose(lo, [-0.005, -0.005, 0.0], atol=1e-15)
    np.testing.assert_allclose(hi, [0.005, 0.005, 0.005], atol=1e-15)


# --- BOP's adi and mspd -----------------------------------------------------------------------------

K_TEST = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])


def bop_adi(R_est, t_est, R_gt, t_gt, pts):
    """bop_toolkit's pose_error.adi, transcribed from its definition: for every model point
    placed by the truth, the distance to the nearest model point placed by the estimate."""
    from scipy.spatial import cKDTree

    pts_est = pts @ R_est.T + t_est
    pts_gt = pts @ R_gt.T + t_gt
    return float(cKDTree(pts_est).query(pts_gt, k=1)[0].mean())


def bop_mspd(R_est, t_est, R_gt, t_gt, K, pts, syms):
    """bop_toolkit's pose_error.mspd, transcribed: symmetries applied to the truth."""

    def project(R, t):
        x = (pts @ R.T + t) @ K.T
        return x[:, :2] / x[:, 2:3]

    p_est = project(R_est, t_est)
    return min(float(np.linalg.norm(p_est - project(R_gt @ S[:3, :3], R_gt @ S[:3, 3] + t_gt), axis=1).max())
               for S in syms)


def test_adi_hand_computed_is_truth_to_nearest_estimate():
    # Points 0, 1 cm along x and 3 cm along y; the estimate is shifted 2 cm along y.
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.03, 0.0]])
    T_est = se3.make_pose(np.eye(3), (0.0, 0.02, 0.0))
    # From the truth's points: (0,0) -> (0,2): 2; (1,0) -> (1,2): 2; (0,3) -> (0,2): 1 cm.
    assert float(M.adi(T_est, np.eye(4), pts)) == pytest.approx(0.05 / 3, abs=1e-12)
    # The other direction (estimate's points to the truth's) would give (1 + sqrt 2 + 2) / 3 cm.
    assert float(M.adi(np.eye(4), T_est, pts)) == pytest.approx((0.03 + math.sqrt(2) * 0.01) / 3, abs=1e-12)


def test_adi_and_mspd_equal_bop_toolkit_definitions(cube_group):
    rng = np.random.default_rng(21)
    pts = rng.normal(0, 0.01, (300, 3)) * [1.0, 0.5, 2.0]
    T_gt = se3.make_pose(Rotation.random(30, random_state=1).as_matrix(), rng.normal(0, 0.02, (30, 3)) + [0, 0, 0.4])
    T_est = T_gt @ se3.exp_se3(rng.normal(0, [0.003] * 3 + [0.3] * 3, (30, 6)))
    ours = M.adi(T_est, T_gt, pts)
    theirs = [bop_adi(a[:3, :3], a[:3, 3], b[:3, :3], b[:3, 3], pts) for a, b in zip(T_est, T_gt)]
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
    # the symmetric cube: values for the configured group as BOP computes them
    cube_pts = M.box_corners((-0.0125, -0.0125, 0.0), (0.0125, 0.0125, 0.025))
    ours = M.mspd(T_est, T_gt, K_TEST, cube_pts, cube_group)
    theirs = [bop_mspd(a[:3, :3], a[:3, 3], b[:3, :3], b[:3, 3], K_TEST, cube_pts, cube_group)
              for a, b in zip(T_est, T_gt)]
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(M.adi(T_est @ cube_group[5], T_est, cube_pts), 0.0, atol=1e-12)


def test_mspd_hand_computed():
    T_gt = se3.make_pose(np.eye(3), (0.0, 0.0, 0.5))  # 0.5 m in front of the camera
    pts = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    # 1 mm along x at 0.5 m: fx * 0.001 / 0.5 = 1.2 px for both points
    T_est = se3.make_pose(np.eye(3), (0.001, 0.0, 0.5))
    assert float(M.mspd(T_est, T_gt, K_TEST, pts)) == pytest.approx(1.2, abs=1e-9)
    # a half turn about z through the object's x midpoint swaps the points: a symmetry of the pair
    swap = rot("z", 180.0, (0.01, 0.0, 0.0))
    assert float(M.mspd(T_gt @ swap, T_gt, K_TEST, pts)) == pytest.approx(600 * 0.01 / 0.5, abs=1e-9)
    assert float(M.mspd(T_gt @ swap, T_gt, K_TEST, pts, swap[None])) == pytest.approx(0.0, abs=1e-9)
