"""The mask-renderer protocol and what every renderer shares: the mesh registry and argument checks.

A renderer turns object poses ``T_sensor_object`` (N, 4, 4) in a sensor's optical frame
into one binary mask per pose in a :class:`~mvtop_cli.render.roi.Roi` of that sensor's image
(paper section IV-B):

- ``"silhouette"`` (camera): pixels where the object is the nearest surface, i.e. not
  hidden behind an occluder (gripper, environment) nearer to the camera;
- ``"tactile"`` (GelSight-style sensor, a pinhole camera looking through the gel): pixels
  where the object's nearest surface lies in front of the undeformed gel plane
  ``z = gel_distance_m``, by more than ``penetration_threshold_m`` (the object presses in).

Occluders are ``(mesh_id, T_sensor_mesh)`` pairs with fixed poses for the call, or
``(PIXEL_OCCLUDER, mask)`` with a full-image mask (H, W) bool: pixels that hide every mesh
rendered, so they carry no evidence (the estimator's excluded contact pixels). Lens
distortion is ignored: observed masks must be undistorted first.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Literal, Protocol, Sequence

import numpy as np

from mvtop_cli.errors import MeshError
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render.iou import iou_scores
from mvtop_cli.render.mesh import RenderMesh
from mvtop_cli.render.roi import Roi

RenderMode = Literal["silhouette", "tactile"]
Occluder = tuple[str, np.ndarray]
PIXEL_OCCLUDER = "pixels"  # an occluder of image pixels (H, W) bool instead of a mesh pose

# Nearest depth rendered [m]; both renderers clip there. A tactile sensor's gel sits ~25 mm
# from its camera and cameras see the object from >= 0.1 m, so 1 mm loses nothing.
DEFAULT_ZNEAR_M = 1e-3


class MaskRenderer(Protocol):
    """Renders all particles of one sensor in one call."""

    def add_mesh(self, mesh_id: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Register a mesh once: ``vertices`` (V, 3) [m] in the mesh frame, ``faces`` (F, 3)."""
        ...

    def render_masks(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
        mode: RenderMode = "silhouette",
        gel_distance_m: float | None = None,
        penetration_threshold_m: float = 0.0,
    ) -> np.ndarray:
        """Masks (N, h, w) bool of mesh ``mesh_id`` at poses (N, 4, 4) in ``roi``."""
        ...

    def render_depth(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
    ) -> np.ndarray:
        """Depth z (N, h, w) float32 [m] of the object's nearest visible surface, ``inf``
        where the object is not seen."""
        ...

    def score_masks(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        observed: np.ndarray,
        occluders: Sequence[Occluder] | None = None,
        mode: RenderMode = "silhouette",
        gel_distance_m: float | None = None,
        penetration_threshold_m: float = 0.0,
        observed_outside: float = 0.0,
        empty_score: float = 1.0,
        depth_limit_m: np.ndarray | None = None,
    ) -> np.ndarray:
        """IoU (N,) float64 of each pose's mask with ``observed`` (h, w) bool in ``roi``; the
        observed pixels a pose comes nearer than ``depth_limit_m`` (h, w) [m] count as missed."""
        ...

    def render_tactile(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        gel_distance_m: float,
        occluders: Sequence[Occluder] | None = None,
        penetration_threshold_m: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tactile masks (N, h, w) bool and gel penetration ``gel_distance_m - z`` clipped at
        0, (N, h, w) float32 [m], from one depth render."""
        ...


def penetration_depth(depth: np.ndarray, gel_distance_m: float) -> np.ndarray:
    """Gel penetration (..., h, w) float32 [m]: ``gel_distance_m - z``, 0 where the surface
    is behind the gel plane or absent (``z = inf``)."""
    d = np.float32(gel_distance_m) - np.asarray(depth, dtype=np.float32)
    return np.maximum(d, np.float32(0.0))


class RendererBase(ABC):
    """Mesh registry, argument checks and the generic parts of :class:`MaskRenderer`."""

    def __init__(self, znear_m: float = DEFAULT_ZNEAR_M) -> None:
        if not znear_m > 0:
            raise ValueError(f"znear_m must be > 0, got {znear_m}")
        self.znear_m = float(znear_m)
        self._meshes: dict[str, RenderMesh] = {}

    def add_mesh(self, mesh_id: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Register (or replace) mesh ``mesh_id``: ``vertices`` (V, 3) [m], ``faces`` (F, 3)."""
        self._meshes[mesh_id] = RenderMesh.from_arrays(vertices, faces, name=f"mesh {mesh_id!r}")

    def mesh(self, mesh_id: str) -> RenderMesh:
        """The registered mesh ``mesh_id``."""
        try:
            return self._meshes[mesh_id]
        except KeyError:
            known = ", ".join(repr(k) for k in self._meshes) or "none"
            raise MeshError(f"mesh {mesh_id!r} is not registered (registered: {known})") from None

    @staticmethod
    def _poses(T_sensor_object: np.ndarray) -> np.ndarray:
        T = np.asarray(T_sensor_object, dtype=np.float64)
        if T.shape[-2:] != (4, 4) or T.ndim not in (2, 3):
            raise ValueError(f"T_sensor_object must be (N, 4, 4) or (4, 4), got {T.shape}")
        T = np.ascontiguousarray(T.reshape(-1, 4, 4))
        if not np.all(np.isfinite(T)):
            raise ValueError("T_sensor_object holds non-finite values")
        return T

    def _occluders(self, occluders: Sequence[Occluder] | None) -> list[tuple[RenderMesh, np.ndarray]]:
        """The mesh occluders as (mesh, T_sensor_mesh); pixel occluders are ``_blocked``'s."""
        out = []
        for mesh_id, T in occluders or ():
            if mesh_id == PIXEL_OCCLUDER:
                continue
            T = np.asarray(T, dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"occluder {mesh_id!r}: pose must be a finite (4, 4), got shape {T.shape}")
            out.append((self.mesh(mesh_id), np.ascontiguousarray(T)))
        return out

    @staticmethod
    def _blocked(occluders: Sequence[Occluder] | None, camera: PinholeCamera, roi: Roi) -> np.ndarray | None:
        """The ROI pixels (h, w) bool hidden by the pixel occluders (``PIXEL_OCCLUDER``), or None."""
        out = None
        for name, mask in occluders or ():
            if name != PIXEL_OCCLUDER:
                continue
            mask = np.asarray(mask)
            if mask.dtype != bool or mask.shape != (camera.height, camera.width):
                raise ValueError(f"pixel occluder must be a ({camera.height}, {camera.width}) bool image mask, "
                                 f"got {mask.dtype} {mask.shape}")
            crop = roi.crop(mask)
            out = crop if out is None else out | crop
        return out

    @staticmethod
    def _tactile_plane(mode: str, gel_distance_m: float | None, penetration_threshold_m: float) -> float | None:
        """Depth [m] in front of which a surface counts as penetrating, or None for silhouettes."""
        if mode == "silhouette":
            return None
        if mode != "tactile":
            raise ValueError(f"unknown render mode {mode!r} (expected 'silhouette' or 'tactile')")
        if gel_distance_m is None or not gel_distance_m > 0:
            raise ValueError(f"tactile mode needs gel_distance_m > 0, got {gel_distance_m}")
        plane = float(gel_distance_m) - float(penetration_threshold_m)
        if not plane > 0:
            raise ValueError(
                f"penetration_threshold_m {penetration_threshold_m} must be below gel_distance_m {gel_distance_m}"
            )
        return plane

    @abstractmethod
    def render_masks(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
        mode: RenderMode = "silhouette",
        gel_distance_m: float | None = None,
        penetration_threshold_m: float = 0.0,
    ) -> np.ndarray:
        """Masks (N, h, w) bool; see :class:`MaskRenderer`."""

    @abstractmethod
    def render_depth(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
    ) -> np.ndarray:
        """Depth (N, h, w) float32 [m], ``inf`` where the object is not seen."""

    def score_masks(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        observed: np.ndarray,
        occluders: Sequence[Occluder] | None = None,
        mode: RenderMode = "silhouette",
        gel_distance_m: float | None = None,
        penetration_threshold_m: float = 0.0,
        observed_outside: float = 0.0,
        empty_score: float = 1.0,
        depth_limit_m: np.ndarray | None = None,
    ) -> np.ndarray:
        """IoU (N,) float64 of each pose's mask with ``observed`` (h, w) bool, the ROI crop of
        the observed mask (:meth:`Roi.crop`); ``observed_outside`` is the observed area outside
        the ROI (:meth:`Roi.outside_area`) and ``empty_score`` the score when both are empty.
        ``depth_limit_m`` (h, w) [m]: the pixels of ``observed`` where a pose comes nearer than
        this (a part pressed deeper into the gel than measured) are left out of its mask, so
        they count as missed (the union is unchanged)."""
        masks = self.render_masks(
            mesh_id, T_sensor_object, camera, roi, occluders, mode, gel_distance_m, penetration_threshold_m
        )
        if depth_limit_m is not None:
            depth = self.render_depth(mesh_id, T_sensor_object, camera, roi, occluders)
            masks = masks & ~((depth < np.asarray(depth_limit_m)) & np.asarray(observed, dtype=bool))
        return iou_scores(masks, observed, observed_outside, empty_score)

    def render_tactile(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        gel_distance_m: float,
        occluders: Sequence[Occluder] | None = None,
        penetration_threshold_m: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Tactile masks (N, h, w) bool and gel penetration (N, h, w) float32 [m] from one
        depth render; ``mask == penetration > penetration_threshold_m``."""
        self._tactile_plane("tactile", gel_distance_m, penetration_threshold_m)
        depth = self.render_depth(mesh_id, T_sensor_object, camera, roi, occluders)
        pen = penetration_depth(depth, gel_distance_m)
        return pen > np.float32(penetration_threshold_m), pen
