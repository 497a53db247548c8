"""Tactile masking backend and the backend registry, on real GelSight frames and synthetic presses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _real_data import REAL_DATA, needs_real_data

from mvtop_cli.errors import ConfigError, EstimationError
from mvtop_cli.masking import base
from mvtop_cli.masking.base import (
    MaskBackend,
    MaskContext,
    PromptableMaskBackend,
    available_backends,
    get_backend,
    register_backend,
    split_prompt,
)
from mvtop_cli.masking.tactile import (
    TactileDifferenceBackend,
    TactileMaskParams,
    change_magnitude,
    depth_mask,
    difference_components,
)
from mvtop_cli.sim.tactile import box_indentation_m, make_background, render_tactile_image, sphere_indentation_m

MM_PER_PX = 0.1245
SHAPE = (120, 160)
REAL = REAL_DATA / "gelsight_taxim" / "dataPack_small.npz"


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def synthetic_press(indentation_m: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(tactile image, noisy no-contact capture) of one sensor for an indentation."""
    background = make_background(*SHAPE, np.random.default_rng(seed))
    no_contact = render_tactile_image(np.zeros(SHAPE, np.float32), MM_PER_PX, background,
                                      np.random.default_rng(1000 + seed))
    image = render_tactile_image(indentation_m, MM_PER_PX, background, np.random.default_rng(2000 + seed))
    return image, no_contact


# -- real GelSight R1.5 presses (Taxim) ------------------------------------------------


@pytest.fixture(scope="module")
def real_errors() -> dict[str, np.ndarray]:
    with np.load(REAL) as data:
        f0, images = data["f0"], data["imgs"]
        centres, radii = data["touch_center"].astype(float), data["touch_radius"].astype(float)
    backend = TactileDifferenceBackend()
    context = MaskContext(background=f0)
    centroid, radius = [], []
    for image, (cx, cy), r in zip(images, centres, radii):
        mask = backend.contact_mask(image, context)
        assert mask.sum() > 0
        rows, cols = np.nonzero(mask)
        centroid.append(math.hypot(cols.mean() - cx, rows.mean() - cy))
        radius.append(math.sqrt(mask.sum() / math.pi) - r)
    return {"centroid_px": np.array(centroid), "radius_px": np.array(radius)}


@needs_real_data
def test_real_presses_centroid_matches_labels(real_errors):
    """Labelled contact centres vs mask centroids over 49 presses of a 4 mm ball.

    Achieved: median 2.55 px (0.32 mm), max 4.7 px. Most of it is a systematic offset of
    the labels: circles fitted to the ring of strongest colour change (independent of the
    mask) sit (+1.2, -1.5) px from the labelled centres in the median
    (scripts/check_gelsight_real.py prints both).
    """
    c = real_errors["centroid_px"]
    assert len(c) == 49
    assert np.median(c) < 3.0
    assert c.max() < 6.0


@needs_real_data
def test_real_presses_radius_matches_labels(real_errors):
    """Equivalent radius sqrt(area/pi) vs labelled radius (15-17 px).

    Achieved: median +1.5 px (0.19 mm), range [-0.7, +4.4] px: the half-maximum region
    includes part of the gel's deformation around the contact.
    """
    r = real_errors["radius_px"]
    assert np.median(np.abs(r)) < 2.5
    assert -3.0 < np.median(r) < 3.0
    assert np.abs(r).max() < 6.0


@needs_real_data
def test_real_no_contact_frame_gives_no_mask():
    with np.load(REAL) as data:
        f0 = data["f0"]
    backend = TactileDifferenceBackend()
    context = MaskContext(background=f0)
    assert backend.proposals(f0, context) == []
    assert not backend.contact_mask(f0, context).any()


# -- synthetic presses of known geometry ------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(("radius_m", "depth_m"), [(2e-3, 0.8e-3), (5e-3, 0.4e-3)])
def test_difference_mask_of_a_sphere_press(seed, radius_m, depth_m):
    rng = np.random.default_rng(seed)
    centre = (rng.uniform(45, 115), rng.uniform(40, 80))
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, centre, radius_m, depth_m)
    image, no_contact = synthetic_press(ind, seed)
    backend = TactileDifferenceBackend(mode="difference")
    mask = backend.contact_mask(image, MaskContext(background=no_contact, indentation_m=ind))
    assert iou(mask, ind > 0) >= 0.8


@pytest.mark.parametrize("seed", range(4))
def test_difference_mask_of_a_peg_face(seed):
    """The flat face of the IndustReal 12 mm rectangular peg (11.96 x 7.91 mm) pressed in."""
    rng = np.random.default_rng(seed)
    ind = box_indentation_m(SHAPE, MM_PER_PX, (rng.uniform(75, 85), rng.uniform(55, 65)),
                            (11.96e-3, 7.91e-3), rng.uniform(0.1e-3, 0.5e-3), rng.uniform(-0.3, 0.3))
    image, no_contact = synthetic_press(ind, seed)
    mask = TactileDifferenceBackend(mode="difference").contact_mask(image, MaskContext(background=no_contact))
    assert iou(mask, ind > 0) >= 0.8


def test_difference_mask_includes_the_deformation_band_and_refine_removes_it():
    """The image changes around a flat face too (the gel relaxes there): the difference
    region extends ~1.2 x the combined blur beyond the edges; removing the undeformed
    pixels before binarising (the paper's depth refinement) recovers the face."""
    size_m = (7.96e-3, 6.91e-3)  # IndustReal 8 mm rectangular peg
    ind = box_indentation_m(SHAPE, MM_PER_PX, (80, 60), size_m, 0.3e-3, 0.2)
    image, no_contact = synthetic_press(ind, 0)
    truth = ind > 0
    diff = TactileDifferenceBackend(mode="difference").contact_mask(image, MaskContext(background=no_contact))
    assert np.all(diff[truth])
    perimeter_px = 2 * (size_m[0] + size_m[1]) * 1e3 / MM_PER_PX
    band_px = (diff.sum() - truth.sum()) / perimeter_px
    assert 1.5 < band_px < 3.5
    refined = TactileDifferenceBackend(mode="refine").contact_mask(
        image, MaskContext(background=no_contact, indentation_m=ind)
    )
    assert not np.any(refined & ~truth)
    assert iou(refined, truth) > 0.95


@pytest.mark.parametrize("threshold_m", [2e-5, 1e-4])
def test_depth_mask_is_exactly_the_thresholded_indentation(threshold_m):
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (70, 50), 2e-3, 0.6e-3)
    ind = ind + box_indentation_m(SHAPE, MM_PER_PX, (130, 90), (2e-3, 2e-3), 0.2e-3)
    image, no_contact = synthetic_press(ind, 3)
    backend = TactileDifferenceBackend(depth_threshold_m=threshold_m)
    context = MaskContext(background=no_contact, indentation_m=ind)
    expected = ind > threshold_m
    np.testing.assert_array_equal(backend.contact_mask(image, context), expected)
    np.testing.assert_array_equal(depth_mask(ind, threshold_m), expected)
    proposals = backend.proposals(image, context)
    assert len(proposals) == 3  # two contacts and their union
    np.testing.assert_array_equal(proposals[-1], expected)
    assert not (proposals[0] & proposals[1]).any()
    # Without a background the depth alone suffices.
    np.testing.assert_array_equal(backend.contact_mask(image, MaskContext(indentation_m=ind)), expected)


def test_no_contact_gives_no_proposals():
    image, no_contact = synthetic_press(np.zeros(SHAPE, np.float32), 5)
    backend = TactileDifferenceBackend(mode="difference")
    assert backend.proposals(image, MaskContext(background=no_contact)) == []
    assert backend.contact_mask(image, MaskContext(background=no_contact)).shape == SHAPE


def test_two_contacts_give_two_proposals_and_their_union():
    a = sphere_indentation_m(SHAPE, MM_PER_PX, (45, 60), 2e-3, 0.7e-3)
    b = sphere_indentation_m(SHAPE, MM_PER_PX, (115, 60), 2e-3, 0.5e-3)
    image, no_contact = synthetic_press(a + b, 1)
    backend = TactileDifferenceBackend(mode="difference")
    context = MaskContext(background=no_contact)
    proposals = backend.proposals(image, context)
    assert len(proposals) == 3
    first, second, union = proposals
    assert first[60, 45] and second[60, 115]  # the deeper press is the stronger one
    np.testing.assert_array_equal(union, first | second)
    np.testing.assert_array_equal(backend.contact_mask(image, context), union)
    assert all(p.dtype == bool and p.shape == SHAPE for p in proposals)


def test_prompt_selects_the_contact_under_the_prompt():
    a = sphere_indentation_m(SHAPE, MM_PER_PX, (45, 60), 2e-3, 0.7e-3)
    b = sphere_indentation_m(SHAPE, MM_PER_PX, (115, 60), 2e-3, 0.7e-3)
    image, no_contact = synthetic_press(a + b, 2)
    backend = TactileDifferenceBackend(mode="difference")
    context = MaskContext(background=no_contact)
    by_points = backend.prompt(image, np.array([[115.0, 60.0]]), context)
    assert by_points[60, 115] and not by_points[60, 45]
    by_mask = backend.prompt(image, a > 0, context)
    assert by_mask[60, 45] and not by_mask[60, 115]
    both = backend.prompt(image, np.array([[45.0, 60.0], [115.0, 60.0]]), context)
    np.testing.assert_array_equal(both, backend.contact_mask(image, context))
    assert not backend.prompt(image, np.array([[80.0, 10.0], [-5.0, 500.0]]), context).any()


def test_roi_box_limits_the_proposals():
    a = sphere_indentation_m(SHAPE, MM_PER_PX, (45, 60), 2e-3, 0.7e-3)
    b = sphere_indentation_m(SHAPE, MM_PER_PX, (115, 60), 2e-3, 0.7e-3)
    image, no_contact = synthetic_press(a + b, 2)
    backend = TactileDifferenceBackend(mode="difference")
    proposals = backend.proposals(image, MaskContext(roi_box=(80, 0, 160, 120), background=no_contact))
    assert len(proposals) == 1
    assert proposals[0][60, 115] and not proposals[0][:, :80].any()


def test_refine_without_depth_falls_back_to_the_difference():
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (80, 60), 2e-3, 0.8e-3)
    image, no_contact = synthetic_press(ind, 0)
    refine = TactileDifferenceBackend(mode="refine").contact_mask(image, MaskContext(background=no_contact))
    diff = TactileDifferenceBackend(mode="difference").contact_mask(image, MaskContext(background=no_contact))
    np.testing.assert_array_equal(refine, diff)


def test_change_magnitude_noise_estimate_matches_the_noise():
    background = make_background(*SHAPE, np.random.default_rng(0))
    a = render_tactile_image(np.zeros(SHAPE, np.float32), MM_PER_PX, background, np.random.default_rng(1), 3.0)
    b = render_tactile_image(np.zeros(SHAPE, np.float32), MM_PER_PX, background, np.random.default_rng(2), 3.0)
    magnitude, noise_std = change_magnitude(a, b, blur_sigma_px=0.0)
    # Difference of two captures: sqrt(2) x 3 DN per channel.
    assert noise_std == pytest.approx(3.0 * math.sqrt(2), rel=0.1)
    assert magnitude.shape == SHAPE
    regions, evidence = difference_components(a, b, TactileMaskParams(mode="difference"))
    assert regions == [] and evidence.shape == (0,)


def test_missing_or_mismatched_inputs_raise():
    image, no_contact = synthetic_press(np.zeros(SHAPE, np.float32), 0)
    backend = TactileDifferenceBackend()
    with pytest.raises(EstimationError, match="no-contact frame"):
        backend.proposals(image, MaskContext())
    with pytest.raises(EstimationError, match="must match"):
        backend.proposals(image, MaskContext(background=no_contact[:60]))
    with pytest.raises(EstimationError, match="indentation"):
        backend.proposals(image, MaskContext(indentation_m=np.zeros((5, 5))))


# -- parameters and the registry --------------------------------------------------------


def test_get_backend_builds_the_tactile_backend_from_config_options():
    backend = get_backend("difference", min_area_px=10, depth_threshold_m=5e-5, convex_hull=False)
    assert isinstance(backend, TactileDifferenceBackend)
    assert isinstance(backend, MaskBackend) and isinstance(backend, PromptableMaskBackend)
    assert backend.params.min_area_px == 10
    assert backend.params.depth_threshold_m == 5e-5
    assert backend.params.convex_hull is False
    assert get_backend("difference", depth_threshold_m=1).params.depth_threshold_m == 1.0
    assert "difference" in available_backends()


def test_unknown_backend_suggests_the_closest_name():
    with pytest.raises(ConfigError, match=r"unknown masking backend 'diference' \(did you mean 'difference'\?\)"):
        get_backend("diference")


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"min_area": 5}, r"unknown option 'min_area' \(did you mean 'min_area_px'\?\)"),
        ({"depth_threshold_m": "0.1mm"}, "is not of type float"),
        ({"convex_hull": 1}, "is not of type bool"),
        ({"min_area_px": 2.5}, "is not of type int"),
        ({"peak_fraction": 1.5}, "peak_fraction"),
        ({"mode": "depht"}, r"did you mean 'depth'\?"),
        ({"depth_threshold_m": -1e-5}, "depth_threshold_m"),
    ],
)
def test_bad_options_raise_config_errors(options, match):
    with pytest.raises(ConfigError, match=match):
        get_backend("difference", **options)


def test_register_backend_adds_a_backend_and_refuses_duplicates(monkeypatch):
    monkeypatch.setattr(base, "_BACKENDS", {})

    class Everything:
        def __init__(self, value: bool = True):
            self.value = value

        def proposals(self, image, context=None):
            return [np.full(image.shape[:2], self.value)]

    register_backend("everything")(Everything)
    backend = get_backend("everything", value=False)
    assert isinstance(backend, MaskBackend) and not isinstance(backend, PromptableMaskBackend)
    assert not backend.proposals(np.zeros((4, 5, 3), np.uint8))[0].any()
    register_backend("everything")(Everything)  # the same factory again is harmless
    with pytest.raises(ValueError, match="already registered"):
        register_backend("everything")(type("Other", (Everything,), {}))
    with pytest.raises(ValueError, match="already registered"):
        register_backend("difference")(Everything)
    register_backend("difference")(TactileDifferenceBackend)  # the built-in itself is fine


def test_split_prompt():
    mask, points = split_prompt(np.ones((4, 5), np.uint8), (4, 5))
    assert points is None and mask.dtype == bool and mask.all()
    mask, points = split_prompt([[1.0, 2.0], [3.0, 4.0]], (4, 5))
    assert mask is None and points.shape == (2, 2)
    with pytest.raises(ValueError, match="prompt"):
        split_prompt(np.zeros((3, 3)), (4, 5))
