"""Soft camera evidence: the per-pixel probability that the object covers a pixel, from the
image's colours alone.

As the region-based trackers model foreground and background (PWP3D, Prisacariu & Reid 2012;
RBOT, Tjaden et al. 2018; SRT3D and ICG, Stoiber et al.), each pixel's colour is looked up in
two colour histograms, of the object and of its surroundings, and ``P(object | colour) =
p_f / (p_f + p_b)`` (equal priors). The histograms are learned per frame from where the grasp
prior places the part, not from the belief: pixels that every one of a fixed set of prior poses
covers are object, pixels that none covers are background (``coverage``, the fraction of prior
silhouettes covering each pixel of the prior's window). Outside the prior's reach the map is 0:
the part cannot be there, whatever colour those pixels have. So no belief enters the map; the
belief only scores poses against it (soft IoU, ``render.iou``). Shadows, dark faces and
highlights whose colours both histograms hold come out near 0.5 instead of being cut away.
"""

from __future__ import annotations

import numpy as np

SURE_OBJECT = 0.9  # covered by at least this fraction of the prior's poses -> object colours
SURE_BACKGROUND = 0.02  # covered by less than this -> background colours; and beyond the prior's reach


def colour_index(image: np.ndarray, bins: int) -> np.ndarray:
    """Histogram bin (h, w) int64 of each pixel of ``image`` (h, w, 3) uint8, ``bins`` levels per channel."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (h, w, 3) uint8 image, got {image.shape} {image.dtype}")
    if not 2 <= bins <= 256 or 256 % bins:
        raise ValueError(f"bins must divide 256 and lie in [2, 256], got {bins}")
    q = (image.astype(np.int64) * bins) // 256
    return (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]


def object_probability(image: np.ndarray, coverage: np.ndarray, bins: int = 16, pseudo_count: float = 1.0,
                       min_object_pixels: int = 8) -> np.ndarray | None:
    """Per-pixel object probability (h, w) float32 in [0, 1] over the window ``image`` (h, w, 3)
    uint8, from the prior's ``coverage`` (h, w) in [0, 1] of the same window: colour histograms
    (``bins`` per channel, ``pseudo_count`` added to every bin of each) of the sure-object pixels
    (coverage >= ``SURE_OBJECT``; where fewer than ``min_object_pixels``, the most covered ones)
    and of the background (coverage < ``SURE_BACKGROUND``); 0 where coverage < ``SURE_BACKGROUND``.
    None when the window holds no object or no background pixel to learn from."""
    cov = np.asarray(coverage, dtype=np.float32)
    if image.shape[:2] != cov.shape:
        raise ValueError(f"image {image.shape[:2]} and coverage {cov.shape} differ in size")
    idx = colour_index(image, bins)
    background = cov < SURE_BACKGROUND
    obj = cov >= SURE_OBJECT
    if obj.sum() < min_object_pixels and cov.max() >= SURE_BACKGROUND:
        obj = cov >= cov.max() * 0.99
    if not obj.any() or not background.any():
        return None
    n = bins ** 3
    p_f = np.bincount(idx[obj], minlength=n) + pseudo_count
    p_b = np.bincount(idx[background], minlength=n) + pseudo_count
    p_f, p_b = p_f / p_f.sum(), p_b / p_b.sum()
    posterior = (p_f / (p_f + p_b)).astype(np.float32)
    return np.where(background, np.float32(0.0), posterior[idx])


def histogram_overlap(image: np.ndarray, a: np.ndarray, b: np.ndarray, bins: int = 16) -> float:
    """Bhattacharyya coefficient in [0, 1] of the colour histograms (``bins`` levels per channel)
    of the pixels ``a`` and ``b`` (h, w) bool of ``image`` (h, w, 3) uint8: 1 when the two sets
    share their colours in the same proportions, 0 when no colour bin holds pixels of both."""
    if not a.any() or not b.any():
        raise ValueError("histogram_overlap needs at least one pixel in each set")
    idx = colour_index(image, bins)
    n = bins ** 3
    p = np.bincount(idx[a], minlength=n) / a.sum()
    q = np.bincount(idx[b], minlength=n) / b.sum()
    return float(np.sqrt(p * q).sum())
