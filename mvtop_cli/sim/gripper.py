"""Parallel-jaw gripper with GelSight-Mini-like fingers: meshes, finger poses, tactile camera.

Finger frame (one per finger, same mesh for both): origin at the centre of the undeformed
gel pad surface, +z the pad normal pointing toward the grasped object, +x along the pad's
long side, +y toward the fingertip (ee +z). For the left finger (at ee +y) that is
``x = ee x, y = ee z, z = ee −y``; the right finger is the left one turned 180° about ee z.
The ee origin (TCP) is midway between the two pad centres (``docs/frames.md``).
"""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.sim.objects import boxes_to_mesh

FINGERS = ("left", "right")

# GelSight Mini: elastomer pad 18.6 x 14.3 mm imaged at 320 x 240 px (about 0.06 mm/px).
GEL_PAD_SIZE_M = (18.6e-3, 14.3e-3)  # (long side, short side) [m]
TACTILE_IMAGE_SIZE = (320, 240)  # (width, height) [px]; image x along the pad's long side

# Finger geometry [mm] in the finger frame.
_PAD_X, _PAD_Y = 18.6, 14.3  # gel pad (long side along x)
_GEL_PROUD = 1.0  # the gel stands this far proud of the finger face, so it touches first
_TIP_MARGIN = 0.8  # finger material below the pad's lower edge: fingertip at y = 7.95 mm
_FINGER_W, _FINGER_H, _FINGER_T = 22.0, 25.0, 8.0  # finger plate incl. the gel
_BODY = (24.0, 23.05, 20.0)  # sensor body behind the plate (x, y, z): camera and lighting
_MOUNT = (16.0, 18.0, 14.0)  # bar up to the gripper jaw (x, y, z)

FINGERTIP_OFFSET_M = (_PAD_Y / 2.0 + _TIP_MARGIN) * 1e-3  # TCP to fingertip along ee +z [m]
FINGER_COLOR_RGBA = (0.60, 0.61, 0.63, 1.0)  # anodised aluminium, grey
GEL_COLOR_RGBA = (0.75, 0.75, 0.78, 1.0)


@functools.lru_cache(maxsize=1)
def _finger_mesh() -> trimesh.Trimesh:
    tip = _PAD_Y / 2.0 + _TIP_MARGIN
    top = tip - _FINGER_H
    bx, by, bz = _BODY
    mx, my, mz = _MOUNT
    back = -_FINGER_T
    ops = [
        # gel pad, its surface the plane z = 0
        (True, ((-_PAD_X / 2, _PAD_X / 2), (-_PAD_Y / 2, _PAD_Y / 2), (-_GEL_PROUD, 0.0))),
        # finger plate
        (True, ((-_FINGER_W / 2, _FINGER_W / 2), (top, tip), (back, -_GEL_PROUD))),
        # sensor body; its camera looks through the gel from z = -gel_distance
        (True, ((-bx / 2, bx / 2), (top, top + by), (back - bz, back))),
        # mount bar to the jaw, above the finger
        (True, ((-mx / 2, mx / 2), (top - my, top), (back - mz, back))),
    ]
    return boxes_to_mesh(ops)


def gripper_meshes() -> dict[str, trimesh.Trimesh]:
    """Finger meshes [m], each in its own finger frame: ``{"left": ..., "right": ...}``.

    Both fingers share one geometry; each call returns fresh copies.
    """
    return {side: _finger_mesh().copy() for side in FINGERS}


def finger_poses(opening_m: float | np.ndarray) -> dict[str, np.ndarray]:
    """Finger poses ``T_ee_finger`` for a finger opening [m] (distance between gel surfaces).

    opening_m : float or (...,) float
        Opening(s) >= 0; the result holds (..., 4, 4) poses for ``"left"`` (at ee +y, pad
        normal −y) and ``"right"`` (at ee −y, pad normal +y).
    """
    opening = np.asarray(opening_m, dtype=np.float64)
    if not np.all(np.isfinite(opening)) or np.any(opening < 0):
        raise ValueError(f"finger opening must be finite and >= 0 m, got {opening_m!r}")
    # columns: finger x, y, z in ee coordinates
    R_left = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    R_right = np.diag([-1.0, -1.0, 1.0]) @ R_left
    poses = {}
    for side, R, sign in (("left", R_left, 1.0), ("right", R_right, -1.0)):
        T = np.zeros(opening.shape + (4, 4))
        T[..., :3, :3] = R
        T[..., 1, 3] = sign * opening / 2.0
        T[..., 3, 3] = 1.0
        poses[side] = T
    return poses


def pad_band_extent(vertices: np.ndarray, edges: np.ndarray, T_ee_object: np.ndarray) -> tuple[float, float] | None:
    """The part's extent ``(y_min, y_max)`` [m] along ee y within the gel pads' band
    ``|z_ee| <= half the pad's short side``: where the pads can squeeze it, not its widest
    extent elsewhere (a flange above or below the pads). ``vertices`` (n, 3) [m] and the mesh's
    unique ``edges`` (e, 2) in the object frame; the band's part of the surface is the vertices
    in it and the edges' crossings of its two planes. None when the part does not reach the band."""
    half = GEL_PAD_SIZE_M[1] / 2.0
    V = trimesh.transformations.transform_points(np.asarray(vertices, dtype=np.float64), T_ee_object)
    e = np.asarray(edges)
    pts = [V[np.abs(V[:, 2]) <= half, 1]]
    for plane in (half, -half):
        z0, z1 = V[e[:, 0], 2], V[e[:, 1], 2]
        cross = (z0 - plane) * (z1 - plane) < 0
        a, b = V[e[cross, 0]], V[e[cross, 1]]
        s = (plane - a[:, 2]) / (b[:, 2] - a[:, 2])
        pts.append(a[:, 1] + s * (b[:, 1] - a[:, 1]))
    y = np.concatenate(pts)
    if len(y) == 0:
        return None
    return float(y.min()), float(y.max())


def T_finger_tactile_optical(gel_distance_m: float = 0.025) -> np.ndarray:
    """Pose (4, 4) of the tactile camera's optical frame in the finger frame.

    The camera sits ``gel_distance_m`` behind the gel surface looking through it: optical z
    is the pad normal (toward the object), x the pad's long side, y toward the fingertip;
    the undeformed gel surface is the plane z = ``gel_distance_m`` in the optical frame.
    """
    if not np.isfinite(gel_distance_m) or gel_distance_m <= 0:
        raise ValueError(f"gel distance must be > 0 m, got {gel_distance_m!r}")
    T = np.eye(4)
    T[2, 3] = -float(gel_distance_m)
    return T


def tactile_camera(gel_distance_m: float = 0.025) -> PinholeCamera:
    """Intrinsics of a GelSight-Mini-like sensor: 320 x 240 px spanning the 18.6 x 14.3 mm
    pad at ``gel_distance_m`` [m] (about 0.058 x 0.060 mm/px), principal point centred."""
    if not np.isfinite(gel_distance_m) or gel_distance_m <= 0:
        raise ValueError(f"gel distance must be > 0 m, got {gel_distance_m!r}")
    (w, h), (sx, sy) = TACTILE_IMAGE_SIZE, GEL_PAD_SIZE_M
    # pinhole: a pad of size s at depth d spans s * f / d pixels; make that the image size
    return PinholeCamera.from_fov(w, h, fx=w * gel_distance_m / sx, fy=h * gel_distance_m / sy)
