"""Image derivatives for the camera contour term (``estimator.edges``) and its config key
(the term in the frame likelihood: ``test_likelihood.py``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.errors import ConfigError
from mvtop_cli.estimator.edges import EdgeImage, image_gradients, roi_gradients
from mvtop_cli.render.roi import Roi

ROOT = Path(__file__).resolve().parents[2]


def _step(h: int = 40, w: int = 60, column: int = 30) -> np.ndarray:
    img = np.zeros((h, w, 3), np.uint8)
    img[:, column:] = 255
    return img


def test_a_vertical_step_has_its_whole_rise_across_the_columns_and_none_down_the_rows():
    gx, gy = image_gradients(_step(), 0.8)
    assert gx.shape == gy.shape == (3, 40, 60) and gx.dtype == np.float32
    # central differences telescope: a row's derivatives sum to the step in L* (0 -> 255 in 8-bit Lab)
    np.testing.assert_allclose(gx[0].sum(axis=1), 255.0, rtol=1e-4)
    assert np.argmax(gx[0, 20]) in (29, 30)
    np.testing.assert_allclose(gy, 0.0, atol=1e-4)
    np.testing.assert_allclose(gx[1:], 0.0, atol=1e-3)  # grey: no a*, b* change


def test_roi_window_is_the_crop_with_zeros_outside_the_image():
    gx, gy = image_gradients(_step(), 0.8)
    rx, ry = roi_gradients(gx, gy, Roi(20, 10, 16, 12))
    np.testing.assert_array_equal(rx, gx[:, 10:22, 20:36])
    np.testing.assert_array_equal(ry, gy[:, 10:22, 20:36])
    ox, _ = roi_gradients(gx, gy, Roi(50, -5, 20, 10))  # 10 columns and 5 rows outside
    assert ox.shape == (3, 10, 20)
    np.testing.assert_array_equal(ox[:, :5], 0.0)
    np.testing.assert_array_equal(ox[:, :, 10:], 0.0)
    np.testing.assert_array_equal(ox[:, 5:, :10], gx[:, :5, 50:60])
    half, _ = roi_gradients(gx, gy, Roi(0, 0, 60, 40, 0.5))
    assert half.shape == (3, 20, 30)
    np.testing.assert_allclose(half[0].sum(axis=1), 255.0 / 2, rtol=1e-3)  # area-averaged, per image pixel


@pytest.mark.parametrize("roi", [Roi(200, 150, 128, 96), Roi(-30, 400, 128, 128), Roi(100, 50, 256, 256, 0.5)],
                         ids=["inside", "past two edges", "downsampled"])
def test_edge_image_is_the_whole_image_derivatives_cut_to_the_roi(roi):
    rng = np.random.default_rng(4)
    image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), (0, 0), 2.0)
    edge = EdgeImage.of(image, roi, 0.8)
    gx, gy = roi_gradients(*image_gradients(image, 0.8), roi)
    np.testing.assert_allclose(edge.gx, gx, rtol=0, atol=1e-4)
    np.testing.assert_allclose(edge.gy, gy, rtol=0, atol=1e-4)
    typical = 0.5 * (np.abs(gx).sum(axis=0) + np.abs(gy).sum(axis=0))
    assert edge.background == pytest.approx(float(np.median(typical)), rel=1e-4)


def test_a_grey_image_is_refused():
    with pytest.raises(ValueError, match=r"expected an \(H, W, 3\) uint8 RGB image, got \(40, 60\) uint8"):
        image_gradients(_step()[:, :, 0], 0.8)


def test_a_negative_gain_is_refused_naming_the_key(tmp_path):
    text = (ROOT / "configs" / "cube.yaml").read_text() + "\nedges:\n  gain: -1.0\n"
    (tmp_path / "meshes").symlink_to(ROOT / "configs" / "meshes")
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(ConfigError, match=r"edges\.gain"):
        load_config(tmp_path / "c.yaml")
