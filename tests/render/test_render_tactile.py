"""Tactile masks and penetration depths against closed-form contact patches."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.geometry import se3
from mvtop_cli.render import Roi, penetration_depth


@pytest.mark.parametrize("depth_m", [0.0002, 0.0005, 0.001])
def test_cube_face_pressed_flat_gives_its_projected_square(scene, fast, depth_m):
    # A 10 mm cube with its face parallel to the gel, pressed in by depth_m: the mask is the
    # face's projection at z = gel - depth_m, a filled square (no holes along the diagonals).
    side = 0.010
    fast.add_mesh("cube10", scene.cube(side).vertices, scene.cube(side).faces)
    z_face = scene.gel_distance_m - depth_m
    T = se3.make_pose(se3.rotvec_to_matrix([0.0, 0.0, 0.0]), [0.0, 0.0, z_face + side / 2])[None]
    masks, pen = fast.render_tactile("cube10", T, scene.tactile, Roi.full(scene.tactile), scene.gel_distance_m)
    m = masks[0]
    ys, xs = np.nonzero(m)
    expected_side_px = side * scene.tactile.fx / z_face
    assert abs((xs.max() - xs.min() + 1) - expected_side_px) <= 1.0
    assert abs((ys.max() - ys.min() + 1) - expected_side_px) <= 1.0
    assert m[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1].all()
    u, v = scene.tactile.project(np.array([0.0, 0.0, z_face]))
    assert abs(xs.mean() - u) < 0.5 and abs(ys.mean() - v) < 0.5
    np.testing.assert_allclose(pen[0][m], depth_m, atol=1e-7)
    assert (pen[0][~m] == 0).all()


@pytest.mark.parametrize("depth_m", [0.0002, 0.0006, 0.001])
def test_sphere_pressed_gives_disc_of_the_cap_radius(scene, fast, depth_m):
    r = 0.005  # the "sphere" mesh of conftest
    T = se3.make_pose(np.eye(3), [0.0005, -0.0003, scene.gel_distance_m - depth_m + r])[None]
    roi = Roi.full(scene.tactile)
    masks = fast.render_masks(
        "sphere", T, scene.tactile, roi, mode="tactile", gel_distance_m=scene.gel_distance_m
    )
    m = masks[0]
    # The cap meets the gel plane in a circle of radius sqrt(2 r d - d^2), at depth gel.
    expected_px = np.sqrt(2 * r * depth_m - depth_m**2) * scene.tactile.fx / scene.gel_distance_m
    radius_px = np.sqrt(m.sum() / np.pi)
    assert abs(radius_px - expected_px) < 1.0, (radius_px, expected_px)
    ys, xs = np.nonzero(m)
    u, v = scene.tactile.project(np.array([0.0005, -0.0003, scene.gel_distance_m]))
    assert abs(xs.mean() - u) < 0.5 and abs(ys.mean() - v) < 0.5
    pen = penetration_depth(fast.render_depth("sphere", T, scene.tactile, roi), scene.gel_distance_m)[0]
    assert abs(pen.max() - depth_m) < 2e-6
    assert ((pen > 0) == m).mean() > 0.999


def test_threshold_shrinks_the_mask_and_no_contact_is_empty(scene, fast):
    r = 0.005
    roi = Roi.full(scene.tactile)
    kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m)
    T = se3.make_pose(np.eye(3), [0.0, 0.0, scene.gel_distance_m - 0.0005 + r])[None]
    plain = fast.render_masks("sphere", T, scene.tactile, roi, **kw)
    shrunk = fast.render_masks("sphere", T, scene.tactile, roi, penetration_threshold_m=2e-4, **kw)
    assert shrunk.sum() < plain.sum() and not (shrunk & ~plain).any()
    expected_px = np.sqrt(2 * r * 3e-4 - 3e-4**2) * scene.tactile.fx / (scene.gel_distance_m - 2e-4)
    assert abs(np.sqrt(shrunk.sum() / np.pi) - expected_px) < 1.0
    lifted = se3.make_pose(np.eye(3), [0.0, 0.0, scene.gel_distance_m + 0.0001 + r])[None]
    assert not fast.render_masks("sphere", lifted, scene.tactile, roi, **kw).any()


def test_render_tactile_matches_render_masks(scene, fast):
    rng = np.random.default_rng(5)
    T = scene.pressed_poses(rng, fast.mesh("connector").vertices, 20)
    roi = Roi(0, 0, 320, 240, 0.5)
    masks, pen = fast.render_tactile(
        "connector", T, scene.tactile, roi, scene.gel_distance_m, penetration_threshold_m=2e-5
    )
    direct = fast.render_masks(
        "connector", T, scene.tactile, roi, mode="tactile", gel_distance_m=scene.gel_distance_m,
        penetration_threshold_m=2e-5,
    )  # fmt: skip
    assert masks.any(axis=(1, 2)).all()
    assert (masks != direct).sum() <= 2  # only float32 rounding ties may differ
    assert pen.dtype == np.float32 and pen.min() == 0.0 and pen.max() <= 0.0011


def _pressed_box(scene, depth_m: float, tilt_rad: float = 0.0) -> np.ndarray:
    """A 10 mm cube's face held against the gel, its nearest point ``depth_m`` into it, turned
    by ``tilt_rad`` about the sensor's x axis (one edge pressed deeper than the other)."""
    side = 0.010
    R = se3.rotvec_to_matrix([tilt_rad, 0.0, 0.0])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * side / 2
    z_min = (corners @ R.T)[:, 2].min()
    return se3.make_pose(R, [0.0, 0.0, scene.gel_distance_m - depth_m - z_min])[None]


@pytest.mark.parametrize("renderer_name", ["fast", "reference"])
def test_depth_limit_counts_what_a_pose_presses_deeper_than_measured_as_missed(scene, renderer_name, request):
    renderer = request.getfixturevalue(renderer_name)
    side = 0.010
    renderer.add_mesh("cube10", scene.cube(side).vertices, scene.cube(side).faces)
    roi = Roi(0, 0, 320, 240, 0.5)
    kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m, penetration_threshold_m=2e-5)
    truth = _pressed_box(scene, 3e-4)
    _, measured = renderer.render_tactile("cube10", truth, scene.tactile, roi, scene.gel_distance_m,
                                          penetration_threshold_m=2e-5)
    observed = measured[0] > 2e-5
    limit = scene.gel_distance_m - measured[0] - 5e-5
    # tilted 1 deg about x with its nearest edge at the measured depth: the same contact mask
    # (the whole face), but one side of it pressed up to 0.17 mm deeper than measured
    tilted = _pressed_box(scene, 3e-4 + np.radians(1.0) * side, np.radians(1.0))
    poses = np.concatenate([truth, tilted])
    plain = renderer.score_masks("cube10", poses, scene.tactile, roi, observed, **kw)
    limited = renderer.score_masks("cube10", poses, scene.tactile, roi, observed, depth_limit_m=limit, **kw)
    assert plain[0] > 0.98 and plain[1] > 0.95  # the masks alone barely tell them apart
    assert limited[0] == pytest.approx(plain[0], abs=1e-9)  # nothing deeper than measured at the truth
    # its depth runs from the measured 0.30 mm to 0.47 mm across the face: beyond the measured
    # depth plus 0.05 mm on (0.47 - 0.35) / 0.17 = 71 % of it, so about 0.29 of the face is left
    assert 0.24 < limited[1] < 0.33
    shallower = _pressed_box(scene, 1e-4)  # pressed less deep: the limit changes nothing
    np.testing.assert_allclose(
        renderer.score_masks("cube10", shallower, scene.tactile, roi, observed, depth_limit_m=limit, **kw),
        renderer.score_masks("cube10", shallower, scene.tactile, roi, observed, **kw), atol=1e-9)
