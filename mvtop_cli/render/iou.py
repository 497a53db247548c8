"""Intersection over union of rendered masks against an observed mask (paper eq. 2's IoU term)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from mvtop_cli import _threads  # noqa: F401  (sets OMP_WAIT_POLICY before any kernel runs)


@njit(cache=True, parallel=True)
def _count(rendered: np.ndarray, observed: np.ndarray, area: np.ndarray, inter: np.ndarray) -> None:
    """Per rendered mask (N, P) uint8 0/1: its area and the sum of ``observed`` (P,) uint8 counts
    over its pixels (a bool mask's 0/1, or a soft mask's levels)."""
    n, p = rendered.shape
    for i in prange(n):
        a = 0
        b = 0
        r = rendered[i]
        for j in range(p):
            if r[j]:
                a += 1
                b += observed[j]
        area[i] = a
        inter[i] = b


def iou_from_counts(
    area: np.ndarray,
    intersection: np.ndarray,
    observed_area: float,
    empty_score: float = 1.0,
) -> np.ndarray:
    """IoU (N,) float64 from rendered areas (N,), intersections (N,) and the observed area
    (all in the same pixel units); ``empty_score`` where both masks are empty."""
    area = np.asarray(area, dtype=np.float64)
    intersection = np.asarray(intersection, dtype=np.float64)
    union = area + float(observed_area) - intersection
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, intersection / union, float(empty_score))
    return iou


def iou_scores(
    rendered: np.ndarray,
    observed: np.ndarray,
    observed_outside: float = 0.0,
    empty_score: float = 1.0,
) -> np.ndarray:
    """IoU of each rendered mask with the observed mask.

    rendered : (N, h, w) bool, one mask per particle
    observed : (h, w) bool, or float in [0, 1]: a soft mask (per-pixel object probability),
        scored as the soft IoU ``sum_R P / (|R| + sum P - sum_R P)`` (``soft_observed``)
    observed_outside : observed area outside this window (e.g. :meth:`Roi.outside_area`),
        added to every union so that a ROI score equals the whole-image score
    empty_score : the score when the rendered and observed masks are both empty (a tactile
        sensor that sees no contact agrees with a particle that predicts none)
    Returns (N,) float64 in [0, 1].
    """
    rendered = np.asarray(rendered)
    observed = np.asarray(observed)
    if rendered.ndim != 3 or rendered.shape[1:] != observed.shape:
        raise ValueError(f"rendered {rendered.shape} must be (N, h, w) with observed (h, w) = {observed.shape}")
    n = rendered.shape[0]
    r = np.ascontiguousarray(rendered, dtype=bool).reshape(n, observed.size).view(np.uint8)
    o, unit = soft_observed(observed)
    area = np.empty(n, dtype=np.int64)
    inter = np.empty(n, dtype=np.int64)
    if n:
        _count(r, o, area, inter)
    return iou_from_counts(area, inter / unit, float(o.sum(dtype=np.int64)) / unit + observed_outside, empty_score)


SOFT_LEVELS = 255  # a soft mask's probabilities are counted in steps of 1/255 of a pixel


def soft_observed(observed: np.ndarray) -> tuple[np.ndarray, int]:
    """An observed mask as the counting kernels take it: (h * w,) uint8 and the count of one
    whole pixel, 1 for a bool mask, ``SOFT_LEVELS`` for a float one (probabilities in [0, 1],
    rounded to that many levels)."""
    observed = np.asarray(observed)
    if observed.dtype == np.bool_:
        return np.ascontiguousarray(observed).reshape(-1).view(np.uint8), 1
    if not np.issubdtype(observed.dtype, np.floating):
        raise ValueError(f"observed mask must be bool or float probabilities, got {observed.dtype}")
    levels = np.rint(np.clip(observed, 0.0, 1.0) * SOFT_LEVELS).astype(np.uint8)
    return np.ascontiguousarray(levels).reshape(-1), SOFT_LEVELS
