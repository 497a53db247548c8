"""Bit-packed masks: IoU tables and non-maximum suppression against plain loops over bool arrays."""

import cv2
import numpy as np
import pytest
from numba import get_num_threads, set_num_threads

from mvtop_cli.bitmasks import intersections, iou_matrix, mask_nms, pack


def loop_iou(a, b, empty_score=1.0):
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else empty_score


def loop_nms(masks, scores, threshold):
    kept = []
    for i in sorted(range(len(scores)), key=lambda i: -scores[i]):  # sorted() is stable
        if all(loop_iou(masks[i], masks[j], 0.0) <= threshold for j in kept):
            kept.append(i)
    return kept


def blob(shape, centre, axes, angle=0.0):
    m = np.zeros(shape, np.uint8)
    cv2.ellipse(m, (int(centre[0]), int(centre[1])), (int(axes[0]), int(axes[1])), angle, 0, 360, 1, -1)
    return m.astype(bool)


def random_masks(rng, n, shape):
    return np.stack([
        blob(shape, rng.uniform(10, 70, 2), rng.uniform(4, 25, 2), rng.uniform(0, 180)) for _ in range(n)
    ])


def disc(shape, centre, radius):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2


def test_iou_matrix_matches_loop_including_empty_masks():
    rng = np.random.default_rng(0)
    rendered = random_masks(rng, 7, (37, 53))  # 1961 pixels: not a whole number of words
    proposals = random_masks(rng, 5, (37, 53))
    rendered[2] = False
    proposals[4] = False
    got = iou_matrix(rendered, proposals)
    want = np.array([[loop_iou(r, p) for p in proposals] for r in rendered])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert got[2, 4] == 1.0  # both empty: empty_score
    assert iou_matrix(rendered[2:3], proposals[4:5], empty_score=0.0)[0, 0] == 0.0


def test_iou_matrix_of_no_masks_and_mismatched_shapes():
    rng = np.random.default_rng(1)
    masks = random_masks(rng, 3, (20, 30))
    assert iou_matrix(masks[:0], masks).shape == (0, 3)
    assert iou_matrix(masks, masks[:0]).shape == (3, 0)
    with pytest.raises(ValueError, match=r"\(3, 20, 30\) and \(2, 20, 31\)"):
        iou_matrix(masks, np.zeros((2, 20, 31), bool))


def test_intersections_do_not_depend_on_the_thread_count():
    rng = np.random.default_rng(2)
    A, B = pack(random_masks(rng, 130, (64, 90))), pack(random_masks(rng, 9, (64, 90)))
    want = np.array([[np.count_nonzero(np.unpackbits((a & b).view(np.uint8))) for b in B] for a in A])
    before = get_num_threads()
    try:
        for threads in sorted({1, before}):
            set_num_threads(threads)
            np.testing.assert_array_equal(intersections(A, B), want)
    finally:
        set_num_threads(before)


def test_mask_nms_keeps_best_of_overlapping():
    a = disc((50, 50), (20, 20), 10)
    a2 = disc((50, 50), (21, 20), 10)
    c = disc((50, 50), (40, 40), 5)
    keep = mask_nms(np.stack([a, c, a2]), np.array([0.8, 0.5, 0.9]), 0.7)
    assert keep.tolist() == [2, 1]
    assert mask_nms(np.zeros((0, 50, 50), bool), np.zeros(0), 0.7).tolist() == []


@pytest.mark.parametrize("threshold", [0.3, 0.6, 0.9])
def test_mask_nms_matches_loop(threshold):
    rng = np.random.default_rng(3)
    masks = random_masks(rng, 60, (48, 77))
    masks[5] = False  # an empty mask overlaps nothing
    scores = np.round(rng.uniform(0, 1, 60), 1)  # ties: the earlier mask first
    assert mask_nms(masks, scores, threshold).tolist() == loop_nms(masks, scores, threshold)
