"""The insertable criterion with a clearance per direction, and the scores of a part with a
continuous symmetry; used by ``pipelines/evaluate.py``'s ``score_poses``.

A directional clearance gives the free travel of the inserted part along the object frame's
lateral axes, ``(towards -x, towards +x)`` and ``(towards -y, towards +y)`` [m] (a splined
shaft: small across the flanks, larger radially). A corner of the insertion box displaced by
``(dx, dy)`` (truth's object frame) uses ``c_x = x_m[1]`` if ``dx > 0`` else ``x_m[0]`` (the
same for y), and the estimate is insertable when every corner satisfies
``(dx / c_x)^2 + (dy / c_y)^2 <= 1``, minimised over the symmetries. With four equal values
``c`` this is ``||(dx, dy)|| <= c``, the per-side criterion of docs/metrics.md.
"""

from __future__ import annotations

import numpy as np

from . import continuous as C
from . import metrics as M


def directional_ratio(D: np.ndarray, corners: np.ndarray, x_m, y_m) -> np.ndarray:
    """``max_c sqrt((dx / c_x)^2 + (dy / c_y)^2)`` (...) of the corners (n, 3) displaced by
    ``D`` (..., 4, 4) (``D p - p``, the truth's object frame): <= 1 means insertable."""
    d = corners @ np.swapaxes(D[..., :3, :3], -1, -2) + (D[..., None, :3, 3] - corners)
    cx = np.where(d[..., 0] > 0, x_m[1], x_m[0])
    cy = np.where(d[..., 1] > 0, y_m[1], y_m[0])
    return np.sqrt((d[..., 0] / cx) ** 2 + (d[..., 1] / cy) ** 2).max(axis=-1)


def insertable(model, T_est: np.ndarray, T_gt: np.ndarray, insertion_error_m: np.ndarray) -> np.ndarray:
    """(N,) bool: within the clearance, per side (``insertion_error_m <= clearance_m``) or, when
    the model has a directional clearance, by :func:`directional_ratio` over the symmetries."""
    if model.directional_clearance is None:
        return insertion_error_m <= model.clearance_m
    x_m, y_m = model.directional_clearance

    def per_pose(D: np.ndarray, p: np.ndarray) -> np.ndarray:
        return directional_ratio(D, p, x_m, y_m)

    if model.continuous_symmetry is not None:
        axis, point = model.continuous_symmetry
        ratio = C.minimise(per_pose, T_est, T_gt, model.insertion_corners, model.group, axis, point)[0]
    else:
        ratio = M.reduce_points(T_est, T_gt, model.insertion_corners, model.group, per_pose)
    return ratio <= 1.0


def continuous_scores(model, T_est: np.ndarray, T_gt: np.ndarray, out: dict) -> np.ndarray:
    """Replace the symmetry-aware entries of ``out`` (score_poses' dict) by their exact minima
    over the continuous group; returns the chosen symmetry ``S`` (N, 4, 4) per pose
    (``T_est @ S`` is the equivalent closest to the truth)."""
    axis, point = model.continuous_symmetry
    G = model.group
    T_est = np.asarray(T_est, dtype=np.float64).reshape(-1, 4, 4)
    max_metric = C.displacement_metric("max")
    _, k, theta = C.minimise(max_metric, T_est, T_gt, model.vertices, G, axis, point)
    S = C.rotation_about(axis, point, theta) @ G[k]
    T_sym = T_est @ S
    out["translation_error_m"] = M.translation_error(T_sym, T_gt)
    out["rotation_error_rad"] = M.rotation_error(T_sym, T_gt)
    out["pose_error_m"] = C.pose_error_bbox(T_est, T_gt, model.corners, G, axis, point)
    out["add_sym_m"] = C.add(T_est, T_gt, model.samples, G, axis, point)
    out["mssd_m"] = C.mssd(T_est, T_gt, model.vertices, G, axis, point)
    out["insertion_error_m"] = C.lateral_displacement(T_est, T_gt, model.insertion_corners, G, axis, point)
    out["symmetry_index"] = k
    return S
