"""A mask proposal prompted by the whole pose belief, not only its mean.

The particles' rendered silhouettes, weighted by the particle weights, give each pixel of a
camera's region of interest the probability that the object covers it. That map is a natural
GrabCut trimap: pixels every likely pose covers are object, pixels no likely pose covers are
background, the band between is left to the colour models. The result follows the image's
own edges, so it is a proposal that Algorithm 1-2 can pick like any other. This extends the
paper's promptable mode (prompt at the converged estimate) to an unconverged belief.

A converged belief's likely poses agree to a fraction of a pixel, so that band shrinks to
nothing and the proposal is the belief's own outline: a belief a pixel off draws the mask
that then scores it best. ``band_px`` keeps at least that many pixels on either side of the
outline undecided (sure object eroded, sure background dilated by it), so the image places
the outline within that reach whatever the belief says.
"""

from __future__ import annotations

import cv2
import numpy as np

_SURE_FG = 0.9  # covered by at least this fraction of the belief -> object
_PROBABLE_FG = 0.5
_SURE_BG = 0.02  # covered by less than this -> background


def belief_probability(rendered: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-pixel probability (h, w) float32 that the object covers a pixel, from rendered
    masks (P, h, w) bool of P poses with weights (P,) (normalised here)."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    P, h, wd = rendered.shape
    return (w @ rendered.reshape(P, -1).astype(np.float64)).reshape(h, wd).astype(np.float32)


def grabcut_from_belief(
    image: np.ndarray, probability: np.ndarray, iterations: int = 4, seed: int = 0, band_px: int = 0
) -> np.ndarray | None:
    """Object mask (h, w) bool in ``image`` (h, w, 3) uint8 RGB, GrabCut initialised from the
    belief ``probability`` (h, w), the band of ``band_px`` pixels on either side of its outline
    left undecided (the module docstring); None when the belief covers no pixel surely or
    GrabCut fails. Deterministic for a given ``seed`` (GrabCut draws from OpenCV's RNG)."""
    prob = np.asarray(probability, dtype=np.float32)
    if image.shape[:2] != prob.shape:
        raise ValueError(f"image {image.shape[:2]} and probability {prob.shape} differ in size")
    if band_px < 0:
        raise ValueError(f"band_px must be >= 0, got {band_px}")
    maybe = (prob >= _SURE_BG).astype(np.uint8)
    sure = (prob >= _SURE_FG).astype(np.uint8)
    if band_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band_px + 1, 2 * band_px + 1))
        maybe = cv2.dilate(maybe, k)
        sure = cv2.erode(sure, k)
    trimap = np.full(prob.shape, cv2.GC_BGD, np.uint8)
    trimap[maybe.astype(bool)] = cv2.GC_PR_BGD
    trimap[prob >= _PROBABLE_FG] = cv2.GC_PR_FGD
    if sure.sum() < 4:  # a silhouette too small or thin for the band: its likeliest pixels are the object
        sure = (prob >= prob.max() * 0.99).astype(np.uint8) if prob.max() > _PROBABLE_FG else sure
    trimap[sure.astype(bool)] = cv2.GC_FGD
    if not (trimap == cv2.GC_FGD).any() or not (trimap == cv2.GC_BGD).any():
        return None
    cv2.setRNGSeed(seed)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(np.ascontiguousarray(image[:, :, ::-1]), trimap, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return None
    mask = (trimap == cv2.GC_FGD) | (trimap == cv2.GC_PR_FGD)
    # keep the components that hold sure-foreground pixels
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.unique(labels[sure.astype(bool) & mask])
    keep = keep[keep > 0]
    return np.isin(labels, keep) if len(keep) else None
