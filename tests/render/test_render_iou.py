"""The IoU scores against a plain loop, and their edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.render import Roi, iou_from_counts, iou_scores, roi_for_particles


def _loop_iou(rendered, observed, outside=0.0, empty=1.0):
    out = []
    for r in rendered:
        inter = np.logical_and(r, observed).sum()
        union = r.sum() + observed.sum() + outside - inter
        out.append(inter / union if union > 0 else empty)
    return np.array(out)


def test_iou_matches_a_loop():
    rng = np.random.default_rng(0)
    rendered = rng.random((37, 45, 61)) < rng.uniform(0.0, 0.6, size=(37, 1, 1))
    rendered[3] = False
    observed = rng.random((45, 61)) < 0.3
    np.testing.assert_allclose(iou_scores(rendered, observed), _loop_iou(rendered, observed), rtol=1e-12)
    np.testing.assert_allclose(
        iou_scores(rendered, observed, observed_outside=17.5), _loop_iou(rendered, observed, 17.5), rtol=1e-12
    )


def test_iou_edge_cases():
    empty = np.zeros((2, 8, 8), dtype=bool)
    np.testing.assert_array_equal(iou_scores(empty, np.zeros((8, 8), bool)), [1.0, 1.0])
    np.testing.assert_array_equal(iou_scores(empty, np.zeros((8, 8), bool), empty_score=0.0), [0.0, 0.0])
    full = np.ones((1, 8, 8), dtype=bool)
    assert iou_scores(full, full[0])[0] == 1.0
    assert iou_scores(full, ~full[0])[0] == 0.0
    assert iou_scores(full, full[0], observed_outside=64.0)[0] == 0.5
    assert iou_scores(np.zeros((0, 8, 8), bool), full[0]).shape == (0,)
    np.testing.assert_array_equal(iou_from_counts([4, 0], [2, 0], 2.0), [0.5, 0.0])
    with pytest.raises(ValueError):
        iou_scores(full, np.ones((8, 9), bool))


def test_fused_scores_equal_iou_of_rendered_masks(scene, fast):
    rng = np.random.default_rng(4)
    T = scene.camera_particles(rng, 64, 0.4)
    roi = roi_for_particles(fast.mesh("connector"), T, scene.camera, max_side=96)
    observed_full = fast.render_masks("connector", T[:1], scene.camera, Roi.full(scene.camera))[0]
    observed = roi.crop(observed_full)
    outside = roi.outside_area(observed_full)
    masks = fast.render_masks("connector", T, scene.camera, roi)
    fused = fast.score_masks("connector", T, scene.camera, roi, observed, observed_outside=outside)
    np.testing.assert_array_equal(fused, iou_scores(masks, observed, observed_outside=outside))
    assert fused.argmax() == 0 and fused[0] > 0.9
