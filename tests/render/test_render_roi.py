"""Regions of interest: placement, intrinsics, area-consistent cropping."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.render import Roi, iou_scores, roi_for_particles, roi_from_bounds


@pytest.mark.parametrize("distance_m", [0.15, 0.3, 0.6])
def test_roi_contains_the_projected_object(scene, fast, distance_m):
    rng = np.random.default_rng(1)
    T = scene.camera_particles(rng, 40, distance_m, spread_m=0.01)
    roi = roi_for_particles(fast.mesh("cube"), T, scene.camera, max_side=100, margin_px=3)
    assert max(roi.shape) <= 100
    assert 0 <= roi.x0 and roi.x0 + roi.width <= 640 and 0 <= roi.y0 and roi.y0 + roi.height <= 480
    full = fast.render_masks("cube", T, scene.camera, Roi.full(scene.camera))
    window = np.zeros((480, 640), dtype=bool)
    window[roi.y0 : roi.y0 + roi.height, roi.x0 : roi.x0 + roi.width] = True
    assert full.any() and not (full & ~window).any()


def test_roi_at_full_scale_equals_the_cropped_full_render(scene, fast):
    rng = np.random.default_rng(2)
    T = scene.camera_particles(rng, 10, 0.3)
    roi = roi_for_particles(fast.mesh("connector"), T, scene.camera, max_side=200)
    assert roi.scale == 1.0
    full = fast.render_masks("connector", T, scene.camera, Roi.full(scene.camera))
    np.testing.assert_array_equal(
        fast.render_masks("connector", T, scene.camera, roi),
        full[:, roi.y0 : roi.y0 + roi.height, roi.x0 : roi.x0 + roi.width],
    )


def test_downsampled_roi_matches_the_cropped_mask(scene, fast):
    # Rendering at 1/k resolution and block-averaging the full render agree up to the
    # boundary pixels, and the IoU computed in the ROI is close to the full-image one.
    rng = np.random.default_rng(3)
    T = scene.camera_particles(rng, 12, 0.3, spread_m=0.01)
    roi = roi_for_particles(fast.mesh("cube"), T, scene.camera, max_side=64)
    assert roi.scale < 1.0
    full = fast.render_masks("cube", T, scene.camera, Roi.full(scene.camera))
    small = fast.render_masks("cube", T, scene.camera, roi)
    for f, s in zip(full, small):
        assert iou_scores(s[None], roi.crop(f))[0] > 0.9
        assert abs(s.sum() / roi.scale**2 - f.sum()) < 0.05 * f.sum()
    observed = full[0]
    full_iou = iou_scores(full, observed)
    roi_iou = iou_scores(small, roi.crop(observed), observed_outside=roi.outside_area(observed))
    assert np.abs(full_iou - roi_iou).max() < 0.05 and roi_iou.argmax() == 0


def test_roi_camera_maps_pixels_consistently(scene):
    roi = Roi(100, 60, 120, 90, 1 / 3)
    cam = roi.camera(scene.camera)
    assert (cam.height, cam.width) == roi.shape == (30, 40)
    p = np.array([[0.01, -0.02, 0.5], [-0.03, 0.01, 0.4]])
    u, v = scene.camera.project(p).T
    ur, vr = cam.project(p).T
    # The ROI pixel whose block holds image pixel centre (u, v).
    np.testing.assert_allclose(ur, (u + 0.5 - 100) / 3 - 0.5)
    np.testing.assert_allclose(vr, (v + 0.5 - 60) / 3 - 0.5)
    # Image pixels 100..102 form ROI pixel 0: its centre is image pixel 101.
    assert Roi(100, 60, 120, 90, 1 / 3).camera(scene.camera).project(
        np.array([(101 - scene.camera.cx) / scene.camera.fx, 0.0, 1.0])
    )[0] == pytest.approx(0.0)


def test_crop_is_area_consistent_and_paste_inverts_it():
    mask = np.zeros((480, 640), dtype=bool)
    yy, xx = np.mgrid[:480, :640]
    mask[(xx - 300.3) ** 2 + (yy - 200.7) ** 2 < 37.2**2] = True
    roi = Roi(240, 150, 120, 102, 0.5)
    small = roi.crop(mask)
    assert small.shape == (51, 60)
    assert abs(small.sum() / 0.25 - mask.sum()) < 0.02 * mask.sum()
    np.testing.assert_allclose(roi.coverage(mask).sum() / 0.25, mask.sum())
    back = roi.paste(small, mask.shape)
    assert iou_scores(back[None], mask)[0] > 0.95
    assert roi.outside_area(mask) == 0.0
    half = Roi(300, 0, 340, 480, 1.0)
    assert half.outside_area(mask) == pytest.approx(mask[:, :300].sum())


@pytest.mark.parametrize("roi", [Roi(240, 150, 120, 102), Roi(-7, 430, 60, 80), Roi(600, -5, 64, 40),
                                 Roi(240, 150, 120, 102, 0.5), Roi(-8, 440, 64, 48, 0.25)])
def test_crop_and_outside_area_of_a_bool_mask_equal_the_coverage_route(roi):
    """A bool mask's crop and outside area (counted directly) are the coverage's and the float
    sum's, bit for bit, also where the window leaves the image."""
    rng = np.random.default_rng(3)
    mask = rng.random((480, 640)) < 0.3
    np.testing.assert_array_equal(roi.crop(mask), roi.coverage(mask) >= 0.5)
    np.testing.assert_array_equal(roi.crop(mask, 0.75), roi.coverage(mask) >= 0.75)
    assert roi.outside_area(mask) == roi.outside_sum(mask.astype(np.float32))
    inside = mask[max(roi.y0, 0):roi.y0 + roi.height, max(roi.x0, 0):roi.x0 + roi.width].sum()
    assert roi.outside_area(mask) == (mask.sum() - inside) * roi.scale**2


def test_roi_bounds_are_clipped_to_the_image(scene):
    roi = roi_from_bounds(-50.0, -20.0, 30.0, 10.0, scene.camera, max_side=128)
    assert (roi.x0, roi.y0) == (0, 0) and roi.scale == 1.0
    assert roi.width >= 31 and roi.height >= 11
    roi = roi_from_bounds(-1e4, -1e4, 1e4, 1e4, scene.camera, max_side=128)
    assert roi.x0 >= 0 and roi.x0 + roi.width <= 640 and max(roi.shape) <= 128
    with pytest.raises(ValueError):
        Roi(0, 0, 10, 10, 0.25)  # 2.5 ROI pixels: not a whole number


def test_tactile_roi_bounds_the_contact_only(scene, fast):
    # Tilted connectors touch the gel with part of their face only.
    rng = np.random.default_rng(9)
    T = scene.pressed_poses(
        rng, fast.mesh("connector").vertices, 30, depth_range_m=(0.0002, 0.0004), spread_m=0.0003, max_tilt_rad=0.2
    )
    roi = roi_for_particles(
        fast.mesh("connector"), T, scene.tactile, mode="tactile", gel_distance_m=scene.gel_distance_m
    )
    whole = roi_for_particles(fast.mesh("connector"), T, scene.tactile)
    assert roi.width * roi.height < whole.width * whole.height
    full = fast.render_masks(
        "connector", T, scene.tactile, Roi.full(scene.tactile), mode="tactile", gel_distance_m=scene.gel_distance_m
    )
    window = np.zeros((240, 320), dtype=bool)
    window[roi.y0 : roi.y0 + roi.height, roi.x0 : roi.x0 + roi.width] = True
    assert full.any() and not (full & ~window).any()
    lifted = T.copy()
    lifted[:, 2, 3] += 0.01
    none = roi_for_particles(
        fast.mesh("connector"), lifted, scene.tactile, mode="tactile", gel_distance_m=scene.gel_distance_m
    )
    # No contact: the whole image, downsampled (less a column or two to tile whole pixels).
    assert none.width > 320 - 1 / none.scale and none.height > 240 - 1 / none.scale


def test_maximum_takes_the_deepest_image_pixel_of_each_roi_pixel():
    values = np.zeros((240, 320), dtype=np.float32)
    values[100, 151] = 3e-4  # one deep image pixel
    values[101:103, 150:152] = 1e-4
    roi = Roi(147, 99, 9, 6, 1 / 3)  # 3 x 2 ROI pixels of 3 x 3 image pixels
    small = roi.maximum(values)
    assert small.shape == (2, 3) and small.dtype == np.float32
    # image rows 99-101 / cols 150-152 form ROI pixel (0, 1); rows 102-104 the one below it
    np.testing.assert_array_equal(small, np.float32([[0.0, 3e-4, 0.0], [0.0, 1e-4, 0.0]]))
    assert Roi(0, 0, 320, 240, 1.0).maximum(values)[100, 151] == np.float32(3e-4)
    up = Roi(150, 100, 2, 2, 2.0).maximum(values)  # upsampled: each image pixel repeated 2 x 2
    assert up.shape == (4, 4) and (up[:2, 2:] == np.float32(3e-4)).all() and up[:2, :2].max() == 0.0
    assert Roi(310, 230, 20, 20, 1.0).maximum(values).shape == (20, 20)  # zero beyond the image edge
