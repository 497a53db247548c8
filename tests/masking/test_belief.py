"""The belief-prompted GrabCut proposal (``masking.belief``): the belief's coverage map, and
the band around its outline that the image decides."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.masking.belief import belief_probability, grabcut_from_belief


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def _scene(shift_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 64 x 80 image of a red 24 x 24 square on a noisy blue-grey background, the square's
    mask, and a tight belief's coverage: the same square ``shift_px`` to the right."""
    rng = np.random.default_rng(3)
    image = np.empty((64, 80, 3), np.float64)
    image[...] = (70, 90, 150)
    truth = np.zeros((64, 80), bool)
    truth[20:44, 28:52] = True
    image[truth] = (200, 60, 40)
    image = np.clip(image + rng.normal(0, 8, image.shape), 0, 255).astype(np.uint8)
    belief = np.zeros((64, 80), np.float32)
    belief[20:44, 28 + shift_px:52 + shift_px] = 1.0
    return image, truth, belief


def test_belief_probability_is_the_weighted_share_of_covering_poses():
    masks = np.zeros((3, 4, 5), bool)
    masks[0, :2] = True
    masks[1, :, :3] = True
    masks[2, 3, 4] = True
    p = belief_probability(masks, np.array([2.0, 1.0, 1.0]))
    assert p.dtype == np.float32 and p.shape == (4, 5)
    assert p[0, 0] == pytest.approx(0.75) and p[0, 4] == pytest.approx(0.5)
    assert p[2, 0] == pytest.approx(0.25) and p[3, 4] == pytest.approx(0.25) and p[2, 4] == 0.0


def test_a_band_lets_the_image_place_the_outline_of_a_belief_two_pixels_off():
    image, truth, belief = _scene(2)
    drawn = grabcut_from_belief(image, belief, seed=0, band_px=0)
    # without a band a tight belief is its own mask: sure object inside, sure background outside
    assert _iou(drawn, belief.astype(bool)) == 1.0
    assert _iou(drawn, truth) < 0.85
    banded = grabcut_from_belief(image, belief, seed=0, band_px=3)
    assert _iou(banded, truth) > 0.97  # the square's own edges, not the belief's
    assert _iou(banded, truth) > _iou(banded, belief.astype(bool))
    # the same at the truth: a band costs nothing where the belief is right
    image, truth, belief = _scene(0)
    assert _iou(grabcut_from_belief(image, belief, seed=0, band_px=3), truth) > 0.97


def test_grabcut_is_deterministic_for_a_seed_and_checks_its_inputs():
    image, _, belief = _scene(1)
    a = grabcut_from_belief(image, belief, seed=5, band_px=2)
    b = grabcut_from_belief(image, belief, seed=5, band_px=2)
    np.testing.assert_array_equal(a, b)
    assert grabcut_from_belief(image, np.zeros_like(belief), band_px=2) is None  # nothing surely object
    with pytest.raises(ValueError, match="differ in size"):
        grabcut_from_belief(image, belief[:10], band_px=2)
    with pytest.raises(ValueError, match="band_px"):
        grabcut_from_belief(image, belief, band_px=-1)
