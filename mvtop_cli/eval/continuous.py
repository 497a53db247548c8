"""Pose errors modulo a continuous symmetry (a round peg, a cylinder): exact minima over the angle.

An object that every rotation ``C(theta)`` about an axis (through a point, object frame) maps
onto itself has the symmetry group ``{C(theta) @ G_k}``, ``G`` the finite group of its
other symmetries (identity first; e.g. a cylinder's end-for-end turn). A symmetry-aware
error is the minimum of the plain error over ``T_est @ C(theta) @ G_k`` (the convention of
:mod:`mvtop_cli.eval.metrics`). A finite list of angles leaves a residual of up to half a step
times the part's radius; here the minimum over ``theta`` is found to about 1e-9 rad: the
error is evaluated on a 5 degree grid and the best cell of each ``(pose, G_k)`` pair is
refined by golden-section search, in a bracket of one grid step either side (the errors
are smooth in ``theta`` apart from kinks of the max-type metrics, which golden section
handles as it only compares values).
"""

from __future__ import annotations

import numpy as np

from ..geometry import se3

_GRID_STEPS = 72  # 5 degree grid over the full turn
_GOLDEN_ITERATIONS = 48  # bracket 2 grid steps * 0.618**48 ~ 2e-11 rad
_INV_PHI = (np.sqrt(5.0) - 1.0) / 2.0


def rotation_about(axis: np.ndarray, point: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Rigid transforms (..., 4, 4) rotating by ``theta`` (...) [rad] about the unit ``axis`` (3,)
    through ``point`` (3,) [m] (object frame)."""
    theta = np.asarray(theta, dtype=np.float64)
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    c = np.asarray(point, dtype=np.float64)
    R = se3.rotvec_to_matrix(theta[..., None] * a)
    T = np.zeros(theta.shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = c - R @ c
    T[..., 3, 3] = 1.0
    return T


def displacement_metric(kind: str):
    """``f(D (..., 4, 4), points (n, 3)) -> (...)`` over the displacements ``D p - p``."""

    def f(D: np.ndarray, p: np.ndarray) -> np.ndarray:
        d = p @ np.swapaxes(D[..., :3, :3], -1, -2) + (D[..., None, :3, 3] - p)
        n = np.linalg.norm(d, axis=-1)
        return n.mean(axis=-1) if kind == "mean" else n.max(axis=-1)

    return f


def minimise(per_pose, T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, group: np.ndarray,
             axis: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimum over the continuous group of ``per_pose(D, points)``, ``D = T_gt^-1 T_est C(theta) G_k``.

    per_pose : callable (D (..., 4, 4), points (n, 3)) -> (...)
    T_est, T_gt : (N, 4, 4) ; points (n, 3) object frame [m] ; group (m, 4, 4) identity first.
    Returns ``(value (N,), k (N,) index into group, theta (N,) [rad])`` of the minimum.
    """
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    T_gt = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    G = np.asarray(group, dtype=np.float64).reshape(-1, 4, 4)
    A = se3.invert(T_gt) @ T_est  # (N, 4, 4)

    def f(theta: np.ndarray) -> np.ndarray:  # theta (N, m) -> (N, m)
        D = A[:, None] @ rotation_about(axis, point, theta) @ G[None]
        return per_pose(D, pts)

    step = 2.0 * np.pi / _GRID_STEPS
    grid = np.stack([f(np.full((len(A), len(G)), j * step)) for j in range(_GRID_STEPS)])  # (K, N, m)
    best = np.argmin(grid, axis=0)
    a, b = (best - 1) * step, (best + 1) * step
    c, d = b - _INV_PHI * (b - a), a + _INV_PHI * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(_GOLDEN_ITERATIONS):
        left = fc < fd  # the minimum lies in [a, d]: d becomes the upper end, c the new d
        a, b = np.where(left, a, c), np.where(left, d, b)
        new_c, new_d = b - _INV_PHI * (b - a), a + _INV_PHI * (b - a)
        f_new = f(np.where(left, new_c, new_d))
        c, d = np.where(left, new_c, d), np.where(left, c, new_d)
        fc, fd = np.where(left, f_new, fd), np.where(left, fc, f_new)
    theta = 0.5 * (a + b)
    value = f(theta)
    grid_best = np.take_along_axis(grid, best[None], axis=0)[0]
    use_grid = grid_best < value  # never worse than the grid
    theta = np.where(use_grid, best * step, theta)
    value = np.where(use_grid, grid_best, value)
    k = np.argmin(np.round(value, 15), axis=-1)
    rows = np.arange(len(A))
    return value[rows, k], k, theta[rows, k]



def add(T_est, T_gt, points, group, axis, point) -> np.ndarray:
    """ADD [m] minimised over the continuous group (as :func:`metrics.add` over a finite one)."""
    return minimise(displacement_metric("mean"), T_est, T_gt, points, group, axis, point)[0]


def pose_error_bbox(T_est, T_gt, corners, group, axis, point) -> np.ndarray:
    """The paper's bounding-box error [m] minimised over the continuous group."""
    return add(T_est, T_gt, corners, group, axis, point)


def mssd(T_est, T_gt, points, group, axis, point) -> np.ndarray:
    """MSSD [m] minimised over the continuous group (as :func:`metrics.mssd`)."""
    return minimise(displacement_metric("max"), T_est, T_gt, points, group, axis, point)[0]


def lateral_displacement(T_est, T_gt, points, group, axis, point, insertion_axis=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Insertion error [m] (:func:`metrics.lateral_displacement`) minimised over the continuous group."""
    z = np.asarray(insertion_axis, dtype=np.float64)
    z = z / np.linalg.norm(z)

    def per_pose(D: np.ndarray, p: np.ndarray) -> np.ndarray:
        d = p @ np.swapaxes(D[..., :3, :3], -1, -2) + (D[..., None, :3, 3] - p)
        d = d - (d @ z)[..., None] * z
        return np.linalg.norm(d, axis=-1).max(axis=-1)

    return minimise(per_pose, T_est, T_gt, points, group, axis, point)[0]


def closest_in_rotation(T_est, T_gt, group, axis, point) -> np.ndarray:
    """The symmetry ``S = C(theta) @ G_k`` (N, 4, 4) whose equivalent ``T_est @ S`` has the
    rotation closest to the truth's (geodesic angle; ``theta`` in closed form,
    ``se3.best_turn_about_axis``). The rotation error left then has no component about the
    axis: what NEES compares with a covariance summarised modulo the symmetry
    (estimator/symmetry.py), which has none there either."""
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    T_gt = np.asarray(T_gt, dtype=np.float64).reshape(-1, 4, 4)
    G = np.asarray(group, dtype=np.float64).reshape(-1, 4, 4)
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    # trace(R_gt^T R_est C(theta) G_k) = trace(M_k C(theta)) with M_k = G_k R_gt^T R_est
    M = np.einsum("mij,nkj,nkl->nmil", G[:, :3, :3], T_gt[:, :3, :3], T_est[:, :3, :3])
    theta, score = se3.best_turn_about_axis(M, a)
    k = np.argmax(score, axis=1)
    rows = np.arange(len(T_est))
    return rotation_about(a, point, theta[rows, k]) @ G[k]


def closest_equivalent(T_est, T_gt, points, group, axis, point) -> np.ndarray:
    """The symmetric equivalent ``T_est @ C(theta) @ G_k`` (N, 4, 4) closest to the truth by the
    MSSD criterion (largest distance of ``points``), as :func:`metrics.closest_symmetry` picks
    among a finite group."""
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    _, k, theta = minimise(displacement_metric("max"), T_est, T_gt, points, group, axis, point)
    G = np.asarray(group, dtype=np.float64).reshape(-1, 4, 4)
    return T_est @ rotation_about(axis, point, theta) @ G[k]
