"""Soft camera evidence from colour (``masking.colour``): object and background histograms
learned where the grasp prior places the part, each pixel's posterior looked up by its colour."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.masking.colour import SURE_BACKGROUND, colour_index, histogram_overlap, object_probability


def _scene(rng: np.random.Generator):
    """A 60 x 80 window: a red part (rows 20-39, columns 25-54) with a dark red shadowed
    lower edge, on green-grey clutter with a few red specks far from the part; the prior's coverage
    falls from 1 in the part's core to 0 at 8 pixels from it."""
    image = np.empty((60, 80, 3), np.uint8)
    image[:] = (90, 140, 90)
    image += rng.integers(0, 30, size=image.shape, dtype=np.uint8)
    image[20:40, 25:55] = (200, 30, 30)
    image[38:40, 25:55] = (70, 10, 10)  # a dark face the prior is unsure of: in neither histogram
    image[2:5, 2:5] = (200, 30, 30)  # red specks beyond the prior's reach
    yy, xx = np.mgrid[:60, :80]
    dist = np.maximum(np.maximum(20 - yy, yy - 39), np.maximum(25 - xx, xx - 54))  # < 0 inside the part
    coverage = np.clip((8.0 - dist) / 12.0, 0.0, 1.0).astype(np.float32)
    return image, coverage


def test_the_part_is_likely_its_surroundings_not_and_unknown_colours_undecided():
    image, coverage = _scene(np.random.default_rng(0))
    p = object_probability(image, coverage, bins=16)
    assert p.shape == (60, 80) and p.dtype == np.float32
    assert p[22:33, 27:53].min() > 0.95  # the part's lit colour: learned as object
    assert np.all((p[38:40, 25:55] > 0.3) & (p[38:40, 25:55] < 0.7))  # the dark face: undecided, not cut away
    near = (coverage > SURE_BACKGROUND) & (coverage < 0.5)
    near[20:40, 25:55] = False
    assert np.median(p[near]) < 0.05  # clutter around the part: background
    assert np.all(p[coverage < SURE_BACKGROUND] == 0.0)  # beyond the prior's reach, red or not
    assert p[3, 3] == 0.0


def test_a_small_part_learns_from_its_most_covered_pixels():
    image, coverage = _scene(np.random.default_rng(1))
    p = object_probability(image, coverage * 0.5, bins=16)  # no pixel is surely the part
    assert p is not None and p[22:33, 27:53].min() > 0.9


def test_no_background_or_no_part_to_learn_from_gives_none():
    image, coverage = _scene(np.random.default_rng(2))
    assert object_probability(image, np.ones_like(coverage)) is None
    assert object_probability(image, np.zeros_like(coverage)) is None


def test_colour_index_checks_its_input():
    img = np.zeros((2, 2, 3), np.uint8)
    img[0, 0] = (255, 255, 255)
    assert colour_index(img, 16)[0, 0] == 16 ** 3 - 1 and colour_index(img, 16)[1, 1] == 0
    with pytest.raises(ValueError, match="bins must divide 256"):
        colour_index(img, 10)
    with pytest.raises(ValueError, match=r"\(h, w, 3\) uint8"):
        colour_index(img.astype(np.float32), 16)
    with pytest.raises(ValueError, match="differ in size"):
        object_probability(img, np.zeros((3, 2)))


def test_histogram_overlap_is_one_for_shared_colours_and_zero_for_disjoint_ones():
    image = np.zeros((4, 6, 3), np.uint8)
    image[:, :2] = (250, 250, 245)  # white
    image[:, 2:4] = (20, 20, 22)  # black
    image[:, 4:] = (248, 252, 240)  # another white, in the same bins
    cols = np.broadcast_to(np.arange(6), (4, 6))
    white_a, black, white_b = cols < 2, (cols >= 2) & (cols < 4), cols >= 4
    assert histogram_overlap(image, white_a, white_b) == pytest.approx(1.0)
    assert histogram_overlap(image, white_a, black) == 0.0
    # half of one set in the other's colour: sqrt(0.5 * 1) = 0.707
    assert histogram_overlap(image, white_a | black, white_b) == pytest.approx(np.sqrt(0.5))
    with pytest.raises(ValueError, match="at least one pixel in each set"):
        histogram_overlap(image, white_a, np.zeros((4, 6), bool))
