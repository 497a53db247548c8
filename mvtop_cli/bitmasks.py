"""Bit-packed boolean masks: packing, popcount, IoU tables and non-maximum suppression.

Masks (N, h, w) bool are flattened and packed 64 pixels to a uint64 word (``pack``); areas and
intersections are popcounts of the words and of their AND. The counts are integers, so every
result here is exact for any mask size and does not depend on the number of threads.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.extending import intrinsic

from mvtop_cli import _threads  # noqa: F401  (sets OMP_WAIT_POLICY before any kernel runs)


@intrinsic
def popcount(typingctx, x):
    """Set bits of a uint64 (LLVM's ctpop: one instruction where the CPU has it); for numba
    kernels."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return types.uint64(types.uint64), codegen


def pack(masks: np.ndarray) -> np.ndarray:
    """(N, h, w) bool -> (N, words) uint64, each mask flattened and packed 64 pixels a word
    (zero-padded to whole words)."""
    m = np.ascontiguousarray(masks, dtype=bool)
    packed = np.packbits(m.reshape(m.shape[0], int(np.prod(m.shape[1:]))), axis=1)
    pad = (-packed.shape[1]) % 8
    if pad:
        packed = np.pad(packed, ((0, 0), (0, pad)))
    return packed.view(np.uint64)


def areas(words: np.ndarray) -> np.ndarray:
    """Set pixels (N,) int64 of packed masks ``words`` (N, words)."""
    return np.bitwise_count(words).sum(axis=1, dtype=np.int64)


@njit(cache=True, parallel=True)
def _intersections(A, B, out):
    """Popcount of ``A[i] & B[j]`` into ``out[i, j]``; A (N, W), B (M, W) uint64."""
    n, w = A.shape
    m = B.shape[0]
    for i in prange(n):
        for j in range(m):
            s = 0
            for k in range(w):
                s += popcount(A[i, k] & B[j, k])
            out[i, j] = s


def intersections(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Pixels in common (N, M) int64 of packed masks ``A`` (N, W) and ``B`` (M, W); only the
    words some mask of ``B`` touches are visited."""
    used = B.any(axis=0)
    out = np.empty((A.shape[0], B.shape[0]), dtype=np.int64)
    if A.shape[0] and B.shape[0]:
        _intersections(np.ascontiguousarray(A[:, used]), np.ascontiguousarray(B[:, used]), out)
    return out


def iou_matrix(a: np.ndarray, b: np.ndarray, empty_score: float = 1.0) -> np.ndarray:
    """IoU (N, M) float64 in [0, 1] of every mask of ``a`` (N, h, w) bool with every mask of
    ``b`` (M, h, w) bool; ``empty_score`` where both are empty (1: a tactile sensor proposing
    "no contact" agrees with a pose that predicts none, as in ``render.iou``; 0: no match)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.ndim != 3 or b.ndim != 3 or a.shape[1:] != b.shape[1:]:
        raise ValueError(f"masks {a.shape} and {b.shape} must be (N, h, w) and (M, h, w)")
    A, B = pack(a), pack(b)
    inter = intersections(A, B)
    union = (areas(A)[:, None] + areas(B)[None, :] - inter).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, float(empty_score))


@njit(cache=True)
def _greedy_nms(words, area, threshold, kept):
    """Indices into ``words`` (N, W) (best first) that survive greedy suppression at IoU
    ``threshold``, written to ``kept``; returns how many."""
    n, w = words.shape
    count = 0
    for i in range(n):
        drop = False
        for q in range(count):
            j = kept[q]
            s = 0
            for k in range(w):
                s += popcount(words[i, k] & words[j, k])
            if s / max(area[i] + area[j] - s, 1) > threshold:
                drop = True
                break
        if not drop:
            kept[count] = i
            count += 1
    return count


def mask_nms(masks: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression by mask IoU.

    masks : (N, h, w) bool; scores : (N,) float
    Returns the indices (K,) int64 of the kept masks, best score first: a mask is dropped
    when its IoU with a better-scored kept mask exceeds ``iou_threshold`` (ties keep the
    earlier mask).
    """
    scores = np.asarray(scores, np.float64)
    if len(scores) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(-scores, kind="stable")
    words = pack(np.asarray(masks)[order])
    kept = np.empty(len(order), np.int64)
    count = _greedy_nms(words, areas(words), float(iou_threshold), kept)
    return order[kept[:count]]
