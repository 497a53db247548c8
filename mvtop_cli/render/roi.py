"""Regions of interest: the image window (possibly downsampled) in which particles are rendered and scored.

Pixel convention (OpenCV): the centre of full-image pixel ``(row r, column c)`` is at
``(u, v) = (c, r)`` and the pixel covers ``[c - 0.5, c + 0.5) x [r - 0.5, r + 0.5)``.
A :class:`Roi` covers full-image columns ``x0 .. x0 + width - 1`` and rows
``y0 .. y0 + height - 1``; each ROI pixel covers ``1 / scale`` image pixels on a side, so the
ROI image is ``(height * scale, width * scale)`` pixels, following the same convention in its
own coordinates (:meth:`Roi.camera` gives the matching intrinsics).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.geometry.se3 import transform_points
from mvtop_cli.render.mesh import RenderMesh

# Points closer than this to the sensor's optical centre cannot be projected meaningfully
# (the object would be inside the lens); a ROI then falls back to the whole image.
_MIN_PROJECTABLE_Z_M = 1e-4


@dataclass(frozen=True)
class Roi:
    """A crop window of a full image, rendered at ``scale`` ROI pixels per image pixel.

    x0, y0 : int, first image column and row covered
    width, height : int, extent in image pixels; ``width * scale`` and ``height * scale``
        must be whole numbers (the ROI image size)
    scale : float, ROI pixels per image pixel (``1 / k`` for a ``k``-fold downsampling)
    """

    x0: int
    y0: int
    width: int
    height: int
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or not self.scale > 0:
            raise ValueError(f"Roi needs width, height >= 1 and scale > 0, got {self}")
        for name, extent in (("width", self.width), ("height", self.height)):
            n = extent * self.scale
            if abs(n - round(n)) > 1e-6 or round(n) < 1:
                raise ValueError(
                    f"Roi {name} {extent} times scale {self.scale} = {n} is not a whole number of pixels"
                )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the ROI image."""
        return int(round(self.height * self.scale)), int(round(self.width * self.scale))

    @staticmethod
    def full(camera: PinholeCamera) -> "Roi":
        """The whole image at full resolution."""
        return Roi(0, 0, int(camera.width), int(camera.height), 1.0)

    def camera(self, camera: PinholeCamera) -> PinholeCamera:
        """Intrinsics of the ROI image: a point at image pixel ``(u, v)`` lands at ROI pixel
        ``((u + 0.5 - x0) * scale - 0.5, (v + 0.5 - y0) * scale - 0.5)``."""
        s = self.scale
        K = np.array(
            [
                [camera.fx * s, 0.0, (camera.cx + 0.5 - self.x0) * s - 0.5],
                [0.0, camera.fy * s, (camera.cy + 0.5 - self.y0) * s - 0.5],
                [0.0, 0.0, 1.0],
            ]
        )
        rows, cols = self.shape
        return PinholeCamera(width=cols, height=rows, K=K)

    def image(self, image: np.ndarray) -> np.ndarray:
        """The ROI window of an (H, W) or (H, W, C) image, any dtype, at ROI resolution:
        area-averaged when the ROI is downsampled, nearest neighbour when upsampled, zero
        outside the image."""
        win = self._crop(image)
        rows, cols = self.shape
        if (rows, cols) == win.shape[:2]:
            return win
        interp = cv2.INTER_AREA if self.scale < 1 else cv2.INTER_NEAREST
        return cv2.resize(win, (cols, rows), interpolation=interp)

    def _bounds(self, image_shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
        """(ys, ye, xs, xe): the image rows and columns the window covers inside an image of
        ``image_shape`` (H, W, ...), or None when it lies wholly outside."""
        H, W = image_shape[:2]
        ys, xs = max(self.y0, 0), max(self.x0, 0)
        ye, xe = min(self.y0 + self.height, H), min(self.x0 + self.width, W)
        return (ys, ye, xs, xe) if ye > ys and xe > xs else None

    def _crop(self, image: np.ndarray) -> np.ndarray:
        """The ROI's window of ``image`` (H, W, ...) at image resolution, in its dtype,
        zero-padded outside the image."""
        win = np.zeros((self.height, self.width) + image.shape[2:], image.dtype)
        b = self._bounds(image.shape)
        if b is not None:
            ys, ye, xs, xe = b
            win[ys - self.y0 : ye - self.y0, xs - self.x0 : xe - self.x0] = image[ys:ye, xs:xe]
        return win

    def _window(self, image: np.ndarray) -> np.ndarray:
        """The ROI window of ``image`` (H, W) as float32 coverage, zero-padded outside the image."""
        return self._crop(np.asarray(image, dtype=np.float32))

    def coverage(self, mask: np.ndarray) -> np.ndarray:
        """Fraction (h, w) float32 in [0, 1] of each ROI pixel covered by the full-image
        ``mask`` (H, W) bool, by area averaging."""
        return self.average(np.asarray(mask, dtype=bool))

    def average(self, values: np.ndarray) -> np.ndarray:
        """The full-image map ``values`` (H, W) (e.g. a per-pixel probability) averaged over the
        image pixels each ROI pixel covers: (h, w) float32, zero outside the image."""
        # INTER_AREA averages exactly the image pixels each ROI pixel covers.
        return self._reduce(values, lambda win, rows, cols: cv2.resize(win, (cols, rows), interpolation=cv2.INTER_AREA))

    def maximum(self, values: np.ndarray) -> np.ndarray:
        """The full-image map ``values`` (H, W) reduced to the ROI by the largest value among the
        image pixels each ROI pixel covers: (h, w) float32, zero outside the image (nearest
        neighbour when the ROI is upsampled)."""
        k = max(1, int(round(1.0 / self.scale)))
        return self._reduce(values, lambda win, rows, cols: win.reshape(rows, k, cols, k).max(axis=(1, 3)))

    def _reduce(self, values: np.ndarray, downsample) -> np.ndarray:
        """``values`` (H, W) in the ROI window as float32 at ROI resolution: as it is at scale 1,
        each image pixel repeated when upsampled, ``downsample(window, rows, cols)`` otherwise."""
        win = self._window(np.asarray(values, dtype=np.float32))
        rows, cols = self.shape
        if (rows, cols) == win.shape:
            return win
        if self.scale > 1.0:
            # Upsampling: each ROI pixel lies inside one image pixel.
            k = int(round(self.scale))
            return np.repeat(np.repeat(win, k, axis=0), k, axis=1)
        return downsample(win, rows, cols)

    def crop(self, mask: np.ndarray, threshold: float = 0.5) -> np.ndarray:
        """Full-image ``mask`` (H, W) bool -> ROI mask (h, w) bool: a ROI pixel is set when at
        least ``threshold`` of its area is covered, so the mask area is preserved on average.
        At full resolution a pixel is covered wholly or not at all: the window itself."""
        mask = np.asarray(mask)
        if mask.dtype == bool and self.shape == (self.height, self.width) and 0.0 < threshold <= 1.0:
            return self._crop(mask)
        return self.coverage(mask) >= threshold

    def outside_area(self, mask: np.ndarray) -> float:
        """Area of ``mask`` (H, W) bool outside the ROI window, in ROI pixels (image pixels
        times ``scale**2``); pass it to the IoU so scores cover the whole image."""
        m = np.asarray(mask, dtype=bool)
        b = self._bounds(m.shape)
        inside = 0 if b is None else np.count_nonzero(m[b[0]:b[1], b[2]:b[3]])
        return float((np.count_nonzero(m) - inside) * self.scale**2)

    def outside_sum(self, values: np.ndarray) -> float:
        """The sum of the full-image map ``values`` (H, W) outside the ROI window, in ROI pixels:
        :meth:`outside_area` of a soft mask."""
        m = np.asarray(values, dtype=np.float32)
        inside = self._window(m).sum(dtype=np.float64)
        return float((m.sum(dtype=np.float64) - inside) * self.scale**2)

    def paste(self, roi_image: np.ndarray, image_shape: tuple[int, int], fill=0) -> np.ndarray:
        """Place a ROI image (h, w) back into a full image of ``image_shape`` (H, W) (nearest
        neighbour), ``fill`` elsewhere; the inverse of :meth:`crop` for visualisation."""
        roi_image = np.asarray(roi_image)
        rows, cols = self.shape
        if roi_image.shape[:2] != (rows, cols):
            raise ValueError(f"ROI image shape {roi_image.shape[:2]} != ROI shape {(rows, cols)}")
        # Image pixel (r, c) takes ROI pixel floor((r - y0 + 0.5) * scale).
        iy = np.floor((np.arange(self.height) + 0.5) * self.scale).astype(int).clip(0, rows - 1)
        ix = np.floor((np.arange(self.width) + 0.5) * self.scale).astype(int).clip(0, cols - 1)
        window = roi_image[iy][:, ix]
        out = np.full(tuple(image_shape) + roi_image.shape[2:], fill, dtype=roi_image.dtype)
        b = self._bounds(tuple(image_shape))
        if b is not None:
            ys, ye, xs, xe = b
            out[ys:ye, xs:xe] = window[ys - self.y0 : ye - self.y0, xs - self.x0 : xe - self.x0]
        return out


def roi_from_bounds(
    u_min: float,
    v_min: float,
    u_max: float,
    v_max: float,
    camera: PinholeCamera,
    max_side: int = 128,
    margin_px: float = 4.0,
) -> Roi:
    """Smallest ROI inside the image holding the pixel box ``[u_min, u_max] x [v_min, v_max]``
    (image pixel coordinates) plus ``margin_px``, downsampled by the smallest integer factor
    that keeps both sides at most ``max_side`` ROI pixels.

    Integer factors make every ROI pixel exactly ``k x k`` image pixels, so cropping an
    observed mask is an exact block average. Parts of the box outside the image are dropped.
    """
    W, H = int(camera.width), int(camera.height)
    if max_side < 1:
        raise ValueError(f"max_side must be >= 1, got {max_side}")
    # Image pixel c covers [c - 0.5, c + 0.5).
    x_lo = int(np.clip(math.floor(u_min + 0.5 - margin_px), 0, W - 1))
    x_hi = int(np.clip(math.floor(u_max + 0.5 + margin_px), 0, W - 1))
    y_lo = int(np.clip(math.floor(v_min + 0.5 - margin_px), 0, H - 1))
    y_hi = int(np.clip(math.floor(v_max + 0.5 + margin_px), 0, H - 1))
    x_hi, y_hi = max(x_hi, x_lo), max(y_hi, y_lo)
    w, h = x_hi - x_lo + 1, y_hi - y_lo + 1
    k = max(1, math.ceil(max(w, h) / max_side))

    def fit(lo: int, extent: int, limit: int) -> tuple[int, int]:
        n = math.ceil(extent / k)
        if n * k > limit:  # rounding up to whole ROI pixels would leave the image
            n = max(1, limit // k)
        size = n * k
        start = lo - (size - extent) // 2
        return int(np.clip(start, 0, max(limit - size, 0))), size

    x0, width = fit(x_lo, w, W)
    y0, height = fit(y_lo, h, H)
    return Roi(x0, y0, width, height, 1.0 / k)


def roi_for_particles(
    mesh: RenderMesh,
    T_sensor_object: np.ndarray,
    camera: PinholeCamera,
    mode: str = "silhouette",
    gel_distance_m: float | None = None,
    max_side: int = 128,
    margin_px: float = 4.0,
) -> Roi:
    """ROI holding the object's projection for every particle.

    mesh : the object mesh (its convex hull is projected)
    T_sensor_object : (N, 4, 4) or (4, 4) object poses in the sensor's optical frame
    mode : ``"silhouette"`` bounds the whole object; ``"tactile"`` bounds only the part in
        front of the gel plane ``z = gel_distance_m``, where a tactile mask can be non-empty
        (the whole image, downsampled, when no particle touches the gel)
    Points at or behind the optical centre make the ROI the whole image.
    """
    T = np.asarray(T_sensor_object, dtype=np.float64).reshape(-1, 4, 4)
    p = transform_points(T, mesh.hull_vertices)  # (N, H, 3)
    full = (-0.5, -0.5, camera.width - 0.5, camera.height - 0.5)
    if mode == "silhouette":
        pts = p.reshape(-1, 3)
    elif mode == "tactile":
        if gel_distance_m is None or not gel_distance_m > 0:
            raise ValueError(f"tactile ROI needs gel_distance_m > 0, got {gel_distance_m}")
        plane = float(gel_distance_m)
        front = p[..., 2] < plane
        a = p[:, mesh.hull_edges[:, 0]]
        b = p[:, mesh.hull_edges[:, 1]]
        za, zb = a[..., 2] - plane, b[..., 2] - plane
        cross = (za * zb) < 0.0
        t = np.where(cross, za / np.where(cross, za - zb, 1.0), 0.0)
        cut = (a + t[..., None] * (b - a))[cross]
        pts = np.concatenate([p[front], cut], axis=0)
        if len(pts) == 0:
            return roi_from_bounds(*full, camera, max_side=max_side, margin_px=0.0)
    else:
        raise ValueError(f"unknown render mode {mode!r} (expected 'silhouette' or 'tactile')")
    if np.any(pts[:, 2] <= _MIN_PROJECTABLE_Z_M):
        return roi_from_bounds(*full, camera, max_side=max_side, margin_px=0.0)
    uv = camera.project(pts)
    return roi_from_bounds(
        uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max(), camera, max_side, margin_px
    )
