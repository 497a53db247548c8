"""Observations as labelled point sets, the input of point-set registration baselines (pure numpy).

Two labels, as CHSEL's semantics: ``SURFACE`` points lie on the object's surface (its signed
distance is 0 there), ``FREE`` points lie where the object is not (outside it). They come from:

- tactile sensors: the gel surface seen through the tactile camera, where the indentation
  depth says the object presses it, is object surface; every pixel's ray just behind the
  (pressed or undeformed) gel surface runs through the gel and the sensor body, which the
  object cannot occupy: free;
- cameras: rays through background pixels (not in the object mask) that pass near the object
  cross empty space up to the first environment surface they meet (space carving): free;
- the fixed environment: points inside its solids (receptacle, board) cannot be inside the
  object: free.

Pixel convention: OpenCV (the centre of pixel (row r, column c) is at (u, v) = (c, r)); camera
frames are optical (x right, y down, z forward); depths are z distances [m].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from ...geometry import se3
from ...geometry.camera import PinholeCamera

SURFACE = 0  # chsel.SemanticsClass.SURFACE
FREE = 1  # chsel.SemanticsClass.FREE


@dataclass(frozen=True)
class LabelledPoints:
    """Points (N, 3) float64 [m] in one frame with labels (N,) int8, ``SURFACE`` or ``FREE``."""

    points: np.ndarray
    labels: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        lab = np.asarray(self.labels, dtype=np.int8).reshape(-1)
        if len(p) != len(lab):
            raise ValueError(f"{len(p)} points but {len(lab)} labels")
        if np.any((lab != SURFACE) & (lab != FREE)):
            raise ValueError(f"labels must be SURFACE ({SURFACE}) or FREE ({FREE})")
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "labels", lab)

    @staticmethod
    def of(points: np.ndarray, label: int) -> "LabelledPoints":
        """All ``points`` (N, 3) with one label."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return LabelledPoints(p, np.full(len(p), label, dtype=np.int8))

    @staticmethod
    def empty() -> "LabelledPoints":
        return LabelledPoints(np.zeros((0, 3)), np.zeros(0, dtype=np.int8))

    @staticmethod
    def concat(parts: "list[LabelledPoints]") -> "LabelledPoints":
        if not parts:
            return LabelledPoints.empty()
        return LabelledPoints(np.concatenate([p.points for p in parts]), np.concatenate([p.labels for p in parts]))

    def __len__(self) -> int:
        return len(self.points)

    @property
    def surface(self) -> np.ndarray:
        """(n, 3) the surface points."""
        return self.points[self.labels == SURFACE]

    @property
    def free(self) -> np.ndarray:
        """(m, 3) the free-space points."""
        return self.points[self.labels == FREE]

    def transformed(self, T_new_old: np.ndarray) -> "LabelledPoints":
        """The same points expressed in another frame: ``p_new = T_new_old @ p_old``."""
        return LabelledPoints(se3.transform_points(T_new_old, self.points), self.labels)

    def downsampled(self, voxel_m: float) -> "LabelledPoints":
        """One point per label and cubic voxel of side ``voxel_m`` [m] (the mean of the points
        in it), in a fixed order (by label, then voxel index): duplicates from overlapping
        frames and pixels count once. Deterministic."""
        if not voxel_m > 0:
            raise ValueError(f"voxel_m must be > 0, got {voxel_m}")
        out = []
        for label in (SURFACE, FREE):
            p = self.points[self.labels == label]
            if len(p) == 0:
                continue
            keys = np.floor(p / voxel_m).astype(np.int64)
            keys -= keys.min(axis=0)
            dims = keys.max(axis=0) + 1
            flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
            _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
            means = np.stack([np.bincount(inverse, weights=p[:, k], minlength=len(counts)) for k in range(3)], axis=1)
            out.append(LabelledPoints.of(means / counts[:, None], label))
        return LabelledPoints.concat(out)


def back_project(camera: PinholeCamera, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points (n, 3) [m] in the optical frame at pixels ``(u, v)`` (n,) and z depths (n,) [m]."""
    u, v, z = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (u, v, z))
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=1)


def _grid_pixels(shape: tuple[int, int], stride_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of every ``stride_px``-th pixel in both directions, centred in the image."""
    H, W = shape
    r0, c0 = (H - 1) % stride_px // 2, (W - 1) % stride_px // 2
    rows, cols = np.mgrid[r0:H:stride_px, c0:W:stride_px]
    return rows.reshape(-1), cols.reshape(-1)


def tactile_points(
    indentation_m: np.ndarray,
    camera: PinholeCamera,
    gel_distance_m: float,
    *,
    contact_threshold_m: float = 2e-5,
    stride_px: int = 2,
    free_offsets_m: tuple[float, ...] = (5e-4, 1e-3),
) -> LabelledPoints:
    """Labelled points in the tactile camera's optical frame from one gel indentation map.

    indentation_m : (H, W) float
        How far the gel surface is pushed towards the camera [m], 0 where undeformed (the
        tactile depth topic). The undeformed gel surface is the plane ``z = gel_distance_m``.
    contact_threshold_m : float
        Indentation above which a pixel is in contact (the object's surface is at
        ``z = gel_distance_m - indentation`` there): SURFACE.
    stride_px : int
        Every ``stride_px``-th pixel in both directions is used.
    free_offsets_m : tuple of float
        For every used pixel, FREE points this far behind the gel surface (towards the
        camera): inside the gel or the sensor, where the object cannot be.
    """
    ind = np.asarray(indentation_m, dtype=np.float64)
    if ind.shape != (camera.height, camera.width):
        raise ValueError(f"indentation map {ind.shape} does not match the camera {(camera.height, camera.width)}")
    if not gel_distance_m > 0:
        raise ValueError(f"gel_distance_m must be > 0, got {gel_distance_m}")
    rows, cols = _grid_pixels(ind.shape, max(1, int(stride_px)))
    d = np.nan_to_num(ind[rows, cols], nan=0.0, posinf=0.0, neginf=0.0)
    surface_z = gel_distance_m - d
    contact = d > contact_threshold_m
    parts = [LabelledPoints.of(back_project(camera, cols[contact], rows[contact], surface_z[contact]), SURFACE)]
    for off in free_offsets_m:
        z = surface_z - off
        ok = z > 0
        parts.append(LabelledPoints.of(back_project(camera, cols[ok], rows[ok], z[ok]), FREE))
    return LabelledPoints.concat(parts)


def camera_free_points(
    object_mask: np.ndarray,
    camera: PinholeCamera,
    centre_m: np.ndarray,
    radius_m: float,
    *,
    occluder_depth_m: np.ndarray | None = None,
    spacing_m: float = 1e-3,
    stride_px: int = 2,
    mask_margin_px: int = 2,
    occluder_margin_m: float = 1e-3,
) -> LabelledPoints:
    """FREE points in the camera's optical frame carved by background pixels near the object.

    A pixel outside the object mask (dilated by ``mask_margin_px``, which absorbs mask
    errors at the outline) sees past the object: its ray is empty from the camera to the
    first surface it meets. Only the ray's part inside the sphere ``(centre_m, radius_m)``
    (optical frame; the region the object can occupy) is sampled, every ``spacing_m`` [m]
    along the ray, and only in front of ``occluder_depth_m`` (H, W) (z depth [m] of the first
    environment surface, ``inf`` where none) minus ``occluder_margin_m``: what lies behind an
    occluding finger or the receptacle's wall is unknown.

    object_mask : (H, W) bool, the observed object mask (True on the object)
    """
    mask = np.asarray(object_mask, dtype=bool)
    if mask.shape != (camera.height, camera.width):
        raise ValueError(f"mask {mask.shape} does not match the camera {(camera.height, camera.width)}")
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    if mask_margin_px > 0 and mask.any():
        mask = ndimage.binary_dilation(mask, iterations=int(mask_margin_px))
    rows, cols = _grid_pixels(mask.shape, max(1, int(stride_px)))
    keep = ~mask[rows, cols]
    rows, cols = rows[keep], cols[keep]
    rays = back_project(camera, cols, rows, np.ones(len(rows)))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    tc = rays @ c  # distance along the unit ray to the point closest to the centre
    d2 = np.sum(c * c) - tc**2
    hit = (d2 < radius_m**2) & (tc > 0)
    rays, tc, rows, cols = rays[hit], tc[hit], rows[hit], cols[hit]
    half = np.sqrt(np.maximum(radius_m**2 - (np.sum(c * c) - tc**2), 0.0))
    t_lo = np.maximum(tc - half, 0.0)
    n_steps = int(np.ceil(2 * radius_m / spacing_m)) + 1
    steps = np.arange(n_steps) * spacing_m
    # the sample depths along each ray on a lattice aligned to the camera (t = k * spacing)
    t = (np.ceil(t_lo / spacing_m) * spacing_m)[:, None] + steps[None, :]
    ok = t <= (tc + half)[:, None]
    if occluder_depth_m is not None:
        occ = np.asarray(occluder_depth_m, dtype=np.float64)
        if occ.shape != mask.shape:
            raise ValueError(f"occluder depth {occ.shape} does not match the camera {mask.shape}")
        z = t * rays[:, 2:3]
        ok &= z < (occ[rows, cols] - occluder_margin_m)[:, None]
    i, j = np.nonzero(ok)
    return LabelledPoints.of(rays[i] * t[i, j][:, None], FREE)


def environment_free_points(
    signed_distance: Callable[[np.ndarray], np.ndarray],
    centre_m: np.ndarray,
    radius_m: float,
    *,
    spacing_m: float = 1e-3,
    margin_m: float = 2.5e-4,
) -> LabelledPoints:
    """FREE points inside the fixed environment's solids, which the object cannot occupy.

    signed_distance : callable, points (n, 3) [m] -> (n,) signed distance to the environment
        [m], negative inside its solids (e.g. ``EnvironmentSDF.query``), in the frame of
        ``centre_m``
    centre_m, radius_m : the sphere (the region the object can occupy) searched, on a cubic
        lattice of spacing ``spacing_m`` aligned to the frame's origin
    margin_m : only points at least this deep inside the environment are kept
    """
    c = np.asarray(centre_m, dtype=np.float64).reshape(3)
    lo = np.floor((c - radius_m) / spacing_m).astype(np.int64)
    hi = np.ceil((c + radius_m) / spacing_m).astype(np.int64)
    axes = [np.arange(a, b + 1) * spacing_m for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[np.sum((grid - c) ** 2, axis=1) <= radius_m**2]
    if len(grid) == 0:
        return LabelledPoints.empty()
    sd = np.asarray(signed_distance(grid), dtype=np.float64).reshape(-1)
    return LabelledPoints.of(grid[sd < -margin_m], FREE)
