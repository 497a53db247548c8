"""SE(3) poses as float64 arrays of shape (..., 4, 4); quaternions are (x, y, z, w).

Naming: ``T_a_b`` is the pose of frame ``b`` expressed in frame ``a``, so that a
point ``p_b`` maps to ``p_a = T_a_b @ p_b`` and ``T_a_c = T_a_b @ T_b_c``.
Translations are in metres, angles in radians.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def identity(n: int | None = None) -> np.ndarray:
    """Identity pose: (4, 4), or (n, 4, 4) when ``n`` is given."""
    if n is None:
        return np.eye(4)
    return np.tile(np.eye(4), (n, 1, 1))


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose from rotation ``R`` (..., 3, 3) and translation ``t`` (..., 3) [m]."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): ``T_b_a`` from ``T_a_b``."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    t = T[..., :3, 3]
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply poses (..., 4, 4) to points (..., n, 3); returns (..., n, 3)."""
    T = np.asarray(T, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", T[..., :3, :3], p) + T[..., None, :3, 3]


def from_quat_xyzw(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose from unit quaternion(s) ``q`` (..., 4) as (x, y, z, w) and translation ``t`` (..., 3)."""
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    R = Rotation.from_quat(flat).as_matrix().reshape(q.shape[:-1] + (3, 3))
    return make_pose(R, t)


def to_quat_xyzw(T: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) as (x, y, z, w) with w >= 0 from poses (..., 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3].reshape(-1, 3, 3)
    q = Rotation.from_matrix(R).as_quat()
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(T.shape[:-2] + (4,))


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) [rad] (SO(3) exponential)."""
    w = np.asarray(w, dtype=np.float64)
    return Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape[:-1] + (3, 3))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) [rad] from rotation matrices (..., 3, 3) (SO(3) logarithm)."""
    R = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def best_turn_about_axis(M: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angle ``theta`` (...) [rad] that maximises ``trace(M @ Exp(theta a))`` for matrices
    ``M`` (..., 3, 3) and the unit axis ``a`` (3,), and that maximum (...). Closed form: by
    Rodrigues the trace is ``A cos(theta) + B sin(theta) + a^T M a`` with ``A = trace(M) - a^T M a``
    and ``B = trace(M [a]x)``, largest at ``theta = atan2(B, A)``. With ``M = R_ref^T R`` this is
    the turn of ``R`` about its own ``a`` axis that brings it closest to ``R_ref`` (geodesic angle)."""
    M = np.asarray(M, dtype=np.float64)
    a = np.asarray(axis, dtype=np.float64)
    aMa = np.einsum("i,...ij,j->...", a, M, a)
    A = np.einsum("...ii->...", M) - aMa
    B = np.einsum("...ij,ji->...", M, _skew(a))
    return np.arctan2(B, A), np.hypot(A, B) + aMa


def _skew(w: np.ndarray) -> np.ndarray:
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian V(w) (..., 3, 3), with series expansions near zero."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _skew(w)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) + a * W + b * (W @ W)


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of twists ``xi`` (..., 6) = (v [m], w [rad]) -> poses (..., 4, 4)."""
    xi = np.asarray(xi, dtype=np.float64)
    v, w = xi[..., :3], xi[..., 3:]
    R = rotvec_to_matrix(w)
    t = np.einsum("...ij,...j->...i", _left_jacobian(w), v)
    return make_pose(R, t)


def log_se3(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm: poses (..., 4, 4) -> twists (..., 6) = (v [m], w [rad])."""
    T = np.asarray(T, dtype=np.float64)
    w = matrix_to_rotvec(T[..., :3, :3])
    v = np.linalg.solve(_left_jacobian(w), T[..., :3, 3][..., None])[..., 0]
    return np.concatenate([v, w], axis=-1)


def perturb(T: np.ndarray, dt: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """Right-perturb poses: translation ``dt`` (..., 3) [m] and rotation vector ``dw`` (..., 3) [rad]
    expressed in the pose's own frame: ``T @ [Exp(dw) | dt]``."""
    return np.asarray(T, dtype=np.float64) @ make_pose(rotvec_to_matrix(dw), dt)


def perturb_about_origin(T_parent_child: np.ndarray, dt_parent: np.ndarray, dw_parent: np.ndarray) -> np.ndarray:
    """Left-perturb poses (..., 4, 4) about the child's own origin: the origin moves by
    ``dt_parent`` (..., 3) [m] along the parent's axes and the child rotates by the rotation
    vector ``dw_parent`` (..., 3) [rad], also in parent axes, about its origin (no lever arm)::

        R' = Exp(dw) @ R        t' = t + dt

    The convention of the in-hand motion model and the grasp prior (``T_ee_object``: ee axes),
    and what ``pose_spread`` measures."""
    T = np.asarray(T_parent_child, dtype=np.float64)
    R = rotvec_to_matrix(dw_parent) @ T[..., :3, :3]
    return make_pose(R, T[..., :3, 3] + np.asarray(dt_parent, dtype=np.float64))


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray | None = None) -> np.ndarray:
    """Geodesic angle [rad] of rotations (..., 3, 3), or between two sets of rotations."""
    R_a = np.asarray(R_a, dtype=np.float64)
    R = R_a if R_b is None else np.swapaxes(R_a, -1, -2) @ np.asarray(R_b, dtype=np.float64)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def interpolate(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Pose between ``T0`` (alpha=0) and ``T1`` (alpha=1): linear translation, slerp rotation."""
    rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
    R = Slerp([0.0, 1.0], rots)([float(alpha)]).as_matrix()[0]
    t = (1.0 - alpha) * np.asarray(T0)[:3, 3] + alpha * np.asarray(T1)[:3, 3]
    return make_pose(R, t)


def weighted_mean(T: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted mean of poses (n, 4, 4): arithmetic mean of translations and the
    quaternion (Markley) average of rotations, a proper rotation average, not an
    average of matrices. ``weights`` (n,) need not be normalised."""
    T = np.asarray(T, dtype=np.float64)
    w = np.ones(len(T)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    t = w @ T[:, :3, 3]
    R = Rotation.from_matrix(T[:, :3, :3]).mean(weights=w).as_matrix()
    return make_pose(R, t)


def pose_spread(T: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean ``(4, 4)`` and covariance ``(6, 6)`` of poses (n, 4, 4) in the tangent
    space at the mean, ordered (x, y, z [m], rx, ry, rz [rad]) with the translation part
    expressed in the parent frame and the rotation part as a left perturbation."""
    T = np.asarray(T, dtype=np.float64)
    w = np.ones(len(T)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mean = weighted_mean(T, w)
    dt = T[:, :3, 3] - mean[:3, 3]
    dw = matrix_to_rotvec(T[:, :3, :3] @ mean[:3, :3].T)
    d = np.concatenate([dt, dw], axis=1)
    cov = (d * w[:, None]).T @ d
    return mean, cov
