"""GelSight-like tactile image synthesis: determinism, locality, shading and realism."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from _real_data import REAL_DATA, needs_real_data

from mvtop_cli.sim.tactile import (
    box_indentation_m,
    gel_surface_m,
    make_background,
    render_tactile_image,
    sphere_indentation_m,
)

MM_PER_PX = 0.1245  # GelSight R1.5 at 120x160 (Taxim data set)
SHAPE = (120, 160)
REAL = REAL_DATA / "gelsight_taxim"


@pytest.fixture
def background() -> np.ndarray:
    return make_background(*SHAPE, np.random.default_rng(7))


def test_same_seed_same_image_other_seed_other_noise(background):
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (80, 60), 2e-3, 0.6e-3)
    a = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(1))
    b = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(1))
    c = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(2))
    assert a.dtype == np.uint8 and a.shape == (*SHAPE, 3)
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    np.testing.assert_array_equal(make_background(*SHAPE, np.random.default_rng(3)),
                                  make_background(*SHAPE, np.random.default_rng(3)))


def test_no_indentation_is_background_plus_noise(background):
    flat = np.zeros(SHAPE, np.float32)
    clean = render_tactile_image(flat, MM_PER_PX, background, np.random.default_rng(0), noise_std=0.0)
    np.testing.assert_array_equal(clean, background)
    noisy = render_tactile_image(flat, MM_PER_PX, background, np.random.default_rng(0), noise_std=2.0)
    residual = noisy.astype(float) - background
    unclipped = (background > 10) & (background < 245)
    assert abs(residual[unclipped].mean()) < 0.05
    assert residual[unclipped].std() == pytest.approx(2.0, rel=0.05)


def test_image_changes_only_near_the_indentation(background):
    ind = box_indentation_m(SHAPE, MM_PER_PX, (70, 55), (3e-3, 2e-3), 0.4e-3, 0.4)
    gel_blur_mm, optics_blur_px = 0.25, 0.7
    img = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(5),
                               gel_blur_mm=gel_blur_mm, optics_blur_px=optics_blur_px)
    flat = render_tactile_image(np.zeros(SHAPE, np.float32), MM_PER_PX, background, np.random.default_rng(5),
                                gel_blur_mm=gel_blur_mm, optics_blur_px=optics_blur_px)
    # Distance [px] from each pixel to the nearest indented pixel.
    distance = cv2.distanceTransform((ind == 0).astype(np.uint8), cv2.DIST_L2, 5)
    reach = math.ceil(3 * gel_blur_mm / MM_PER_PX) + 1 + math.ceil(3 * optics_blur_px)
    far = distance > reach * math.sqrt(2)  # the square kernels reach further on diagonals
    np.testing.assert_array_equal(img[far], flat[far])
    near = distance < 1.5
    assert np.abs(img[near].astype(int) - flat[near]).max() > 40


def test_flat_face_interior_does_not_change(background):
    # The pressed face is flat: far enough inside it the gel looks undeformed.
    ind = box_indentation_m(SHAPE, MM_PER_PX, (80, 60), (8e-3, 6e-3), 0.5e-3)
    img = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(0), noise_std=0.0)
    inside = cv2.distanceTransform((ind > 0).astype(np.uint8), cv2.DIST_L2, 5) > 4
    assert inside.sum() > 500
    np.testing.assert_array_equal(img[inside], background[inside])


def test_gel_surface_follows_the_object_and_relaxes_around_it():
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (80, 60), 2e-3, 0.8e-3)
    surface = gel_surface_m(ind, MM_PER_PX, gel_blur_mm=0.25)
    assert np.all(surface >= ind)
    contact = ind > 0
    ring = (cv2.distanceTransform((~contact).astype(np.uint8), cv2.DIST_L2, 5) > 0) & (
        cv2.distanceTransform((~contact).astype(np.uint8), cv2.DIST_L2, 5) < 2
    )
    assert np.all(surface[ring] > 0)  # the gel around the contact is pulled along
    np.testing.assert_array_equal(gel_surface_m(ind, MM_PER_PX, gel_blur_mm=0.0), ind)


def test_sphere_rim_takes_the_colour_of_the_led_it_faces(background):
    """Red LED lower left, green upper left, blue right, as on the real R1.5 frames."""
    cx, cy, radius_m, depth_m = 80.0, 60.0, 2e-3, 0.8e-3
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (cx, cy), radius_m, depth_m)
    img = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(0), noise_std=0.0)
    change = img.astype(float) - background
    contact_radius_px = math.sqrt(2 * radius_m * depth_m - depth_m**2) * 1e3 / MM_PER_PX
    for channel, azimuth_deg in ((0, 125.0), (1, 235.0), (2, 0.0)):
        a = math.radians(azimuth_deg)
        r = 0.85 * contact_radius_px
        x, y = int(round(cx + r * math.cos(a))), int(round(cy + r * math.sin(a)))
        patch = change[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3).mean(axis=0)
        assert patch[channel] > 25, (channel, patch)
        assert np.argmax(patch) == channel, (channel, patch)
        # The opposite side of the rim faces away from that LED: darker in its channel.
        x, y = int(round(cx - r * math.cos(a))), int(round(cy - r * math.sin(a)))
        assert change[y - 1 : y + 2, x - 1 : x + 2, channel].mean() < 0


def test_sphere_indentation_geometry():
    radius_m, depth_m = 2e-3, 0.5e-3
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (80, 60), radius_m, depth_m)
    assert ind.max() == pytest.approx(depth_m, rel=1e-6)
    assert ind[60, 80] == pytest.approx(depth_m, rel=1e-6)
    contact_radius_px = math.sqrt(2 * radius_m * depth_m - depth_m**2) * 1e3 / MM_PER_PX
    assert math.sqrt((ind > 0).sum() / math.pi) == pytest.approx(contact_radius_px, abs=0.5)


def test_box_indentation_geometry():
    ind = box_indentation_m(SHAPE, MM_PER_PX, (80, 60), (4e-3, 2e-3), 0.3e-3, angle_rad=math.pi / 2)
    rows, cols = np.nonzero(ind)
    assert set(np.unique(ind)) == {0.0, np.float32(0.3e-3)}
    # Rotated by 90 degrees: the 4 mm side runs along image y.
    assert (rows.max() - rows.min() + 1) == pytest.approx(4.0 / MM_PER_PX, abs=1.0)
    assert (cols.max() - cols.min() + 1) == pytest.approx(2.0 / MM_PER_PX, abs=1.0)


@needs_real_data
def test_background_looks_like_the_real_no_contact_frame():
    """Coarse colour layout and levels of the synthetic frame against the real R1.5 f0."""
    with np.load(REAL / "dataPack_small.npz") as data:
        real = data["f0"]
    for seed in range(3):
        synthetic = make_background(*real.shape[:2], np.random.default_rng(seed))
        assert synthetic.shape == real.shape and synthetic.dtype == np.uint8
        for c in range(3):
            coarse_s = cv2.resize(synthetic[..., c].astype(float), (8, 6), interpolation=cv2.INTER_AREA)
            coarse_r = cv2.resize(real[..., c].astype(float), (8, 6), interpolation=cv2.INTER_AREA)
            assert np.corrcoef(coarse_s.ravel(), coarse_r.ravel())[0, 1] > 0.8
            assert abs(synthetic[..., c].mean() - real[..., c].mean()) < 20
        # Smooth: neighbouring pixels differ by a few DN, as on the real frame.
        step = np.abs(np.diff(synthetic.astype(float), axis=1)).mean()
        assert step < 3.0


@needs_real_data
def test_press_changes_the_image_as_much_as_a_real_press():
    """A 2 mm-radius ball pressed 1.2 mm vs the 49 real presses of a 2 mm-radius ball."""
    with np.load(REAL / "dataPack_small.npz") as data:
        f0, presses = data["f0"].astype(float), data["imgs"].astype(float)
    real = np.median([np.percentile(np.linalg.norm(p - f0, axis=-1), 99.5) for p in presses])
    background = make_background(*SHAPE, np.random.default_rng(0))
    ind = sphere_indentation_m(SHAPE, MM_PER_PX, (80, 60), 2e-3, 1.2e-3)
    img = render_tactile_image(ind, MM_PER_PX, background, np.random.default_rng(0))
    synthetic = np.percentile(np.linalg.norm(img.astype(float) - background, axis=-1), 99.5)
    assert 0.6 * real < synthetic < 1.6 * real


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"indentation_m": -np.ones(SHAPE, np.float32) * 1e-4}, ">= 0"),
        ({"indentation_m": np.zeros((10, 10), np.float32)}, "match"),
        ({"indentation_m": np.zeros((*SHAPE, 1), np.float32)}, r"\(H, W\)"),
        ({"mm_per_px": 0.0}, "mm_per_px"),
        ({"noise_std": -1.0}, "noise_std"),
    ],
)
def test_invalid_inputs_raise(background, kwargs, match):
    args = {"indentation_m": np.zeros(SHAPE, np.float32), "mm_per_px": MM_PER_PX, "background": background,
            "rng": np.random.default_rng(0)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        render_tactile_image(**args)
