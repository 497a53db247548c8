"""The batched CPU renderer: all particles of one sensor rasterised by numba in parallel, no GL context."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render import raster
from mvtop_cli.render.base import DEFAULT_ZNEAR_M, Occluder, RendererBase, RenderMode
from mvtop_cli.render.contour import ContourTopology, contour_gradient
from mvtop_cli.render.iou import iou_from_counts, soft_observed
from mvtop_cli.render.mesh import RenderMesh
from mvtop_cli.render.roi import Roi


def _intrinsics(camera: PinholeCamera, roi: Roi) -> tuple[np.ndarray, int, int]:
    cam = roi.camera(camera)
    intr = np.array([cam.fx, cam.fy, cam.cx, cam.cy], dtype=np.float64)
    return intr, int(cam.width), int(cam.height)


class NumbaMaskRenderer(RendererBase):
    """:class:`~mvtop_cli.render.base.MaskRenderer` on a numba rasteriser (parallel over poses).

    Back faces are culled for closed meshes (watertight, outward winding), which changes no
    mask. ``score_masks`` renders and scores in one pass without keeping the masks.
    The first call compiles the kernels (cached on disk by numba afterwards).

    znear_m : near clipping distance [m]
    """

    # Threshold maps kept per occluder poses, window and gel plane: a frame's likelihood calls
    # all render against the same few (one per sensor).
    _THRESHOLD_CACHE_SIZE = 32
    # ``score_masks`` sets runs (``raster.score_runs_kernel``) when the observed mask holds at
    # least this many pixels per front face; below it the byte mask is faster (raster's notes).
    RUNS_MIN_PIXELS_PER_FACE = 64

    def __init__(self, znear_m: float = DEFAULT_ZNEAR_M) -> None:
        super().__init__(znear_m)
        self._thresholds: dict[tuple, np.ndarray | None] = {}
        self._topologies: dict[tuple[str, float], ContourTopology] = {}

    def add_mesh(self, mesh_id: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Register (or replace) mesh ``mesh_id``; threshold maps rendered before, and the mesh's
        contour topologies, are dropped."""
        super().add_mesh(mesh_id, vertices, faces)
        self._thresholds.clear()
        self._topologies = {k: v for k, v in self._topologies.items() if k[0] != mesh_id}

    def _invdepth(self, mesh: RenderMesh, T: np.ndarray, intr: np.ndarray, w: int, h: int, thr: np.ndarray | None):
        """Largest inverse depth (N, h * w) float32 [1/m] of ``mesh`` at poses ``T``; fragments
        not in front of ``thr`` (h * w,) (inverse depths) are dropped when it is given."""
        out = np.zeros((len(T), w * h), dtype=np.float32)
        use_thr = thr is not None
        t = thr if use_thr else np.zeros(1)
        raster.render_invdepth_kernel(
            T, mesh.vertices, mesh.faces, mesh.face_planes, mesh.closed, intr, w, h, self.znear_m,
            t, float(t.min()), use_thr, raster.chunk_count(len(T)), out,
        )  # fmt: skip
        return out

    def _threshold(
        self,
        occluders: Sequence[Occluder] | None,
        camera: PinholeCamera,
        roi: Roi,
        plane_m: float | None,
    ) -> np.ndarray | None:
        """Per-pixel inverse depth (h * w,) float64 a fragment must exceed (read-only; ``inf``
        where a pixel occluder hides everything), or None for none; kept per occluders, window
        and plane."""
        intr, w, h = _intrinsics(camera, roi)
        key = (tuple((m, np.asarray(T).tobytes()) for m, T in occluders or ()), intr.tobytes(), w, h, plane_m)
        if key in self._thresholds:
            return self._thresholds[key]
        occ = self._occluders(occluders)
        blocked = self._blocked(occluders, camera, roi)
        thr = None
        if occ or plane_m is not None or blocked is not None:
            thr = np.zeros(w * h, dtype=np.float64)
            for mesh, T in occ:
                np.maximum(thr, self._invdepth(mesh, T[None], intr, w, h, None)[0], out=thr)
            if plane_m is not None:
                np.maximum(thr, 1.0 / plane_m, out=thr)
            if blocked is not None:
                thr[blocked.reshape(-1)] = np.inf
            thr.flags.writeable = False
        if len(self._thresholds) >= self._THRESHOLD_CACHE_SIZE:
            self._thresholds.clear()
        self._thresholds[key] = thr
        return thr

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
        """Masks (N, h, w) bool of mesh ``mesh_id`` at poses ``T_sensor_object`` (N, 4, 4)."""
        T = self._poses(T_sensor_object)
        mesh = self.mesh(mesh_id)
        plane = self._tactile_plane(mode, gel_distance_m, penetration_threshold_m)
        intr, w, h = _intrinsics(camera, roi)
        thr = self._threshold(occluders, camera, roi, plane)
        out = np.zeros((len(T), w * h), dtype=np.bool_)
        use_thr = thr is not None
        t = thr if use_thr else np.zeros(1)
        raster.render_masks_kernel(
            T, mesh.vertices, mesh.faces, mesh.face_planes, mesh.closed, intr, w, h, self.znear_m,
            t, float(t.min()), use_thr, raster.chunk_count(len(T)), out,
        )  # fmt: skip
        return out.reshape(len(T), h, w)

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
        """IoU (N,) float64 of each pose's mask with ``observed`` (h, w) bool, rendered and
        counted in one pass; arguments as :meth:`RendererBase.score_masks`."""
        T = self._poses(T_sensor_object)
        mesh = self.mesh(mesh_id)
        plane = self._tactile_plane(mode, gel_distance_m, penetration_threshold_m)
        intr, w, h = _intrinsics(camera, roi)
        obs = np.asarray(observed)
        if obs.shape != (h, w):
            raise ValueError(f"observed mask shape {obs.shape} != ROI shape {(h, w)}")
        counts, unit = soft_observed(obs)
        thr = self._threshold(occluders, camera, roi, plane)
        use_thr = thr is not None
        t = thr if use_thr else np.zeros(1)
        t_min = float(t.min())
        area = np.empty(len(T), dtype=np.int64)
        inter = np.empty(len(T), dtype=np.int64)
        args = (T, mesh.vertices, mesh.faces, mesh.face_planes, mesh.closed, intr, w, h, self.znear_m)
        observed_area = float(counts.sum(dtype=np.int64)) / unit
        use_lim = depth_limit_m is not None
        lim, lmin = np.zeros(1), np.zeros((1, 1))
        if use_lim:
            if unit != 1:
                raise ValueError("depth_limit_m needs a bool observed mask")
            # the limit as an inverse depth, never below the mask's own threshold
            lim = np.maximum(1.0 / np.maximum(np.asarray(depth_limit_m, dtype=np.float64).reshape(-1), self.znear_m), t)
            lmin = raster.limit_blocks(lim.reshape(h, w), obs)
        # Runs pay where the observed part covers many pixels per front face (about half the
        # faces of a closed mesh face the camera) and the threshold is the same everywhere.
        if (unit == 1 and t_min == t.max()
                and observed_area >= self.RUNS_MIN_PIXELS_PER_FACE * len(mesh.faces) / 2):
            raster.score_runs_kernel(*args, t_min, use_thr, lim, lmin, use_lim, raster.chunk_count(len(T)),
                                     raster.pack_rows(obs), counts, area, inter)
        else:  # the byte kernel adds each covered pixel's count: a soft mask's probabilities in 1/255 steps
            raster.score_masks_kernel(*args, t, t_min, use_thr, lim, lmin, use_lim, raster.chunk_count(len(T)),
                                      counts, area, inter)
        return iou_from_counts(area, inter / unit, observed_area + observed_outside, empty_score)

    def contour_gradient(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        gx: np.ndarray,
        gy: np.ndarray,
        occluders: Sequence[Occluder] | None = None,
        spacing_px: float = 1.0,
        margin_px: float = 2.0,
        depth_step: float = 0.01,
        crease_deg: float = 30.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The image gradient across the visible projected contour of mesh ``mesh_id``
        at poses ``T_sensor_object`` (N, 4, 4), the contour behind ``occluders`` or within
        ``margin_px`` of an outline of theirs (``depth_step``) left out; ``gx``, ``gy`` (C, h, w)
        the image derivatives in the ROI. Returns (summed gradient (N,), visible samples (N,)):
        ``render.contour.contour_gradient``."""
        T = self._poses(T_sensor_object)
        mesh = self.mesh(mesh_id)
        key = (mesh_id, crease_deg)
        if key not in self._topologies:
            self._topologies[key] = ContourTopology.from_mesh(mesh, crease_deg)
        intr, w, h = _intrinsics(camera, roi)
        thr = self._threshold(occluders, camera, roi, None)
        return contour_gradient(mesh, self._topologies[key], T, camera, roi, gx, gy, thr, spacing_px,
                                margin_px, depth_step, self.znear_m)

    def render_depth(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
    ) -> np.ndarray:
        """Depth z (N, h, w) float32 [m] of the object's nearest visible surface, ``inf``
        where the object is not seen (absent or behind an occluder)."""
        T = self._poses(T_sensor_object)
        mesh = self.mesh(mesh_id)
        intr, w, h = _intrinsics(camera, roi)
        thr = self._threshold(occluders, camera, roi, None)
        iz = self._invdepth(mesh, T, intr, w, h, thr)
        with np.errstate(divide="ignore"):
            depth = np.where(iz > 0, np.float32(1.0) / iz, np.float32(np.inf)).astype(np.float32)
        return depth.reshape(len(T), h, w)
