"""The camera contour term (beyond the paper): image gradients across the projected contour.

Eq. 2 compares whole-pixel masks; a camera mask made with the belief's help can also echo the
belief (issue: evidence from the image). This term reads the RGB image only. Per camera and pose,
each visible sample of the object's projected contour (``render.contour``, one per
``edges.spacing_px``) reads the colour gradient across the contour, ``g`` in CIE Lab units
per image pixel, and adds ``g - g_0`` to a sum: a log-likelihood ratio of "an edge here"
against "no edge here" that is linear in ``g``, with ``g_0`` the level where both are equally
likely, ``edges.background_factor`` times the window's typical gradient (its median over
pixels). The term is ``edges.gain`` times that sum per 100 px of contour, added to eq. 6's
log-likelihood. The outline of the true pose runs along the image's edges to a fraction of a
pixel, so the term peaks there whatever the masks say. Samples hidden by an occluder carry no
evidence either way (a plain mean over the visible samples would instead favour the poses
that hide the contour's weak stretches behind the fingers).

``image_gradients`` makes a camera's derivatives once per frame; ``roi_gradients`` cuts them
to the frame's ROI window at ROI resolution (zero outside the image); ``EdgeImage`` holds
them with the window's background level.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..render.roi import Roi


@dataclass(frozen=True)
class EdgeImage:
    """One camera's derivatives in the frame's ROI: ``gx``, ``gy`` (3, h, w) float32 [CIE Lab
    units per image pixel] and ``background``, the median over the window of the mean absolute
    derivative summed over channels (what a pixel off any edge reads)."""

    gx: np.ndarray
    gy: np.ndarray
    background: float

    @staticmethod
    def of(image: np.ndarray, roi: Roi, blur_sigma_px: float) -> EdgeImage:
        """The derivatives of an (H, W, 3) uint8 RGB ``image`` in ``roi``: those of the whole
        image, computed on the ROI's window and a border as wide as the filters reach (the
        window is a small part of the frame)."""
        H, W = image.shape[:2]
        border = int(np.ceil(4.0 * blur_sigma_px)) + 2  # OpenCV's float Gaussian: radius 4 sigma; Sobel: 1
        x0, y0 = max(roi.x0 - border, 0), max(roi.y0 - border, 0)
        x1, y1 = min(roi.x0 + roi.width + border, W), min(roi.y0 + roi.height + border, H)
        if x1 <= x0 or y1 <= y0:  # the window lies outside the image
            gx = gy = np.zeros((3, *roi.shape), np.float32)
        else:
            local = Roi(roi.x0 - x0, roi.y0 - y0, roi.width, roi.height, roi.scale)
            gx, gy = roi_gradients(*image_gradients(image[y0:y1, x0:x1], blur_sigma_px), local)
        typical = 0.5 * (np.abs(gx).sum(axis=0) + np.abs(gy).sum(axis=0))
        return EdgeImage(gx, gy, float(np.median(typical)))


def image_gradients(image: np.ndarray, blur_sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives (gx, gy), each (3, H, W) float32, of an (H, W, 3) uint8 RGB image in CIE
    Lab (8-bit OpenCV scaling) along columns and rows [units per pixel], after a Gaussian
    blur of ``blur_sigma_px`` (0: none)."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {img.shape} {img.dtype}")
    lab = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2LAB).astype(np.float32)
    gx = np.empty((3, *img.shape[:2]), np.float32)
    gy = np.empty_like(gx)
    for c in range(3):
        ch = cv2.GaussianBlur(lab[..., c], (0, 0), blur_sigma_px) if blur_sigma_px > 0 else lab[..., c]
        # a 3x3 Sobel over 8: the central difference [units/px] after a [1, 2, 1] / 4 smoothing across it
        gx[c] = cv2.Sobel(ch, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
        gy[c] = cv2.Sobel(ch, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    return gx, gy


def roi_gradients(gx: np.ndarray, gy: np.ndarray, roi: Roi) -> tuple[np.ndarray, np.ndarray]:
    """``gx``, ``gy`` (C, H, W) cut to ``roi``'s window at its resolution, (C, h, w) float32
    (``Roi.image``: area-averaged when the ROI is downsampled, zero outside the image). The
    values stay per image pixel."""
    return tuple(np.ascontiguousarray(np.moveaxis(roi.image(np.ascontiguousarray(np.moveaxis(g, 0, -1))), -1, 0))
                 for g in (gx, gy))
