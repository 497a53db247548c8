"""The IoU scores against a plain loop, and their edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.geometry import se3
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


def _loop_soft_iou(rendered, probability, outside=0.0):
    p = np.rint(np.clip(probability, 0, 1) * 255).astype(np.float64) / 255  # the kernels count in 1/255 steps
    inter = np.array([p[r].sum() for r in rendered])
    return inter / (rendered.reshape(len(rendered), -1).sum(axis=1) + p.sum() + outside - inter)


def test_soft_iou_of_a_probability_map():
    """A float observation is a per-pixel object probability, scored as the soft IoU
    sum_R P / (|R| + sum P - sum_R P); a map of 0 and 1 scores as the bool mask does."""
    rng = np.random.default_rng(1)
    rendered = rng.random((23, 40, 52)) < rng.uniform(0.0, 0.6, size=(23, 1, 1))
    probability = rng.random((40, 52)).astype(np.float32)
    np.testing.assert_allclose(iou_scores(rendered, probability, observed_outside=6.5),
                               _loop_soft_iou(rendered, probability, 6.5), rtol=1e-12)
    observed = rng.random((40, 52)) < 0.3
    np.testing.assert_array_equal(iou_scores(rendered, observed.astype(np.float32)), iou_scores(rendered, observed))
    with pytest.raises(ValueError, match="bool or float"):
        iou_scores(rendered, observed.astype(np.uint8))


def test_fused_soft_scores_equal_soft_iou_of_rendered_masks(scene, fast):
    rng = np.random.default_rng(5)
    T = scene.camera_particles(rng, 48, 0.4)
    roi = roi_for_particles(fast.mesh("connector"), T, scene.camera, max_side=96)
    truth = fast.render_masks("connector", T[:1], scene.camera, Roi.full(scene.camera))[0]
    import cv2

    around = cv2.dilate(truth.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    probability = np.where(truth, 0.8, np.where(around, 0.1, 0.0)).astype(np.float32)  # unsure, about pose 0
    masks = fast.render_masks("connector", T, scene.camera, roi)
    observed, outside = roi.average(probability), roi.outside_sum(probability)
    fused = fast.score_masks("connector", T, scene.camera, roi, observed, observed_outside=outside)
    np.testing.assert_allclose(fused, iou_scores(masks, observed, observed_outside=outside), rtol=1e-12)
    assert fused.argmax() == 0


def _two_boxes():
    """A non-convex closed mesh: two overlapping boxes, whose front faces overlap on screen."""
    a = trimesh.creation.box((0.02, 0.006, 0.006))
    b = trimesh.creation.box((0.006, 0.02, 0.012))
    b.apply_translation([0.004, 0.003, -0.002])
    return trimesh.util.concatenate([a, b])


def _force_kernel(fast, kernel, monkeypatch) -> list:
    """Make ``fast`` score by runs wherever it may (``kernel`` "runs") or never ("bytes"); the
    list returned gets an item per runs-kernel call."""
    from mvtop_cli.render import raster

    runs = []
    real = raster.score_runs_kernel
    monkeypatch.setattr(raster, "score_runs_kernel", lambda *a: runs.append(1) or real(*a))
    monkeypatch.setattr(fast, "RUNS_MIN_PIXELS_PER_FACE", 0 if kernel == "runs" else 10**9)
    return runs


@pytest.mark.parametrize("kernel", ["runs", "bytes"])
@pytest.mark.parametrize("case", ["plain", "slanted occluder", "tactile", "tactile occluded", "near plane"])
def test_fused_scores_count_exactly_the_rendered_pixels(scene, fast, case, kernel, monkeypatch):
    # Scoring by runs (whole words of a row at once, bisection where a constant threshold cuts
    # a row) or by a byte mask must give the IoU of the masks rendered pixel by pixel, in every
    # mode; runs serve only thresholds that are one value over the window.
    runs = _force_kernel(fast, kernel, monkeypatch)
    rng = np.random.default_rng(11)
    fast.add_mesh("two_boxes", *(lambda m: (m.vertices, m.faces))(_two_boxes()))
    kw = {}
    if case.startswith("tactile"):
        camera = scene.tactile
        T = scene.pressed_poses(rng, fast.mesh("two_boxes").vertices, 48, depth_range_m=(0.0001, 0.002))
        kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m, penetration_threshold_m=2e-5)
    elif case == "near plane":
        camera = scene.camera
        T = scene.camera_particles(rng, 48, 0.004, spread_m=0.002)  # cut by z = 1 mm
    else:
        camera = scene.camera
        T = scene.camera_particles(rng, 48, 0.12, spread_m=0.003)  # ~100-200 px: rows of 2-4 words
    if case.endswith("occluder") or case.endswith("occluded"):
        # A wall tilted about y through the objects, its edge among them: left of the edge
        # each pixel has its own threshold, right of it the plain one.
        tilt = se3.rotvec_to_matrix(np.array([0.0, 0.6, 0.0]))
        through = T[:, :3, 3].mean(axis=0)
        if case.startswith("tactile"):
            through[2] = scene.gel_distance_m - 0.0005  # among the contact patches
        kw["occluders"] = [("wall", se3.make_pose(tilt, through + tilt @ [-0.1 + 0.001, 0.0, 0.0]))]
    roi = Roi.full(camera) if case == "near plane" else roi_for_particles(fast.mesh("two_boxes"), T, camera)
    masks = fast.render_masks("two_boxes", T, camera, roi, **kw)
    observed = masks[0] ^ (rng.random(masks[0].shape) < 0.05)
    fused = fast.score_masks("two_boxes", T, camera, roi, observed, observed_outside=3.0, **kw)
    assert masks.sum(axis=(1, 2)).min() < masks.sum(axis=(1, 2)).max()  # masks of different areas
    if "occlu" in case:
        plain = fast.render_masks("two_boxes", T, camera, roi, **{k: v for k, v in kw.items() if k != "occluders"})
        assert (plain & ~masks).any() and masks.any()  # the wall hides part of the object, not all
    np.testing.assert_array_equal(fused, iou_scores(masks, observed, observed_outside=3.0))
    assert bool(runs) == (kernel == "runs" and "occlu" not in case)


@pytest.mark.parametrize("kernel", ["runs", "bytes"])
def test_fused_depth_limit_takes_back_exactly_the_observed_pixels_pressed_deeper_than_it(scene, fast, kernel,
                                                                                        monkeypatch):
    # With a depth limit the fused scores (runs or byte mask, blocks of columns skipped where no
    # pixel can pass) must leave out exactly the observed pixels whose rendered depth is nearer
    # than the limit, as the masks and depth maps rendered pixel by pixel say.
    runs = _force_kernel(fast, kernel, monkeypatch)
    rng = np.random.default_rng(12)
    fast.add_mesh("two_boxes", *(lambda m: (m.vertices, m.faces))(_two_boxes()))
    camera = scene.tactile
    T = scene.pressed_poses(rng, fast.mesh("two_boxes").vertices, 48, depth_range_m=(0.0001, 0.001))
    kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m, penetration_threshold_m=2e-5)
    roi = roi_for_particles(fast.mesh("two_boxes"), T, camera)
    masks = fast.render_masks("two_boxes", T, camera, roi, **kw)
    depth = fast.render_depth("two_boxes", T, camera, roi)
    observed = masks[0] ^ (rng.random(masks[0].shape) < 0.05)
    # a limit that varies pixel to pixel around the poses' depths, beyond the gel in places
    limit = (scene.gel_distance_m - rng.uniform(0.0, 0.0008, size=observed.shape)).astype(np.float32)
    fused = fast.score_masks("two_boxes", T, camera, roi, observed, observed_outside=3.0, depth_limit_m=limit, **kw)
    taken = masks & (depth < limit) & observed
    assert taken.any(axis=(1, 2)).sum() > 10 and (masks & observed & ~taken).any()
    np.testing.assert_array_equal(fused, iou_scores(masks & ~taken, observed, observed_outside=3.0))
    assert bool(runs) == (kernel == "runs")
