"""Occluders hide the object where they are nearer to the sensor, and only there; pixel
occluders hide their pixels from every pose."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.geometry import se3
from mvtop_cli.render import NumbaMaskRenderer, roi_for_particles
from mvtop_cli.render.base import PIXEL_OCCLUDER
from mvtop_cli.render.iou import iou_scores


def _setup(scene, fast, n=8):
    rng = np.random.default_rng(21)
    T = scene.camera_particles(rng, n, 0.45, spread_m=0.002)
    roi = roi_for_particles(fast.mesh("cube"), T, scene.camera)
    return T, roi, fast.render_masks("cube", T, scene.camera, roi)


def test_wall_in_front_hides_everything(scene, fast):
    T, roi, _ = _setup(scene, fast)
    wall = [("wall", se3.make_pose(np.eye(3), [0.0, 0.0, 0.3]))]
    assert not fast.render_masks("cube", T, scene.camera, roi, occluders=wall).any()
    assert np.isinf(fast.render_depth("cube", T, scene.camera, roi, occluders=wall)).all()


def test_wall_behind_hides_nothing(scene, fast):
    T, roi, plain = _setup(scene, fast)
    wall = [("wall", se3.make_pose(np.eye(3), [0.0, 0.0, 0.6]))]
    np.testing.assert_array_equal(fast.render_masks("cube", T, scene.camera, roi, occluders=wall), plain)


def test_half_wall_hides_the_pixels_it_covers(scene, fast):
    # The wall's edge is the plane x = 0 at z = 0.35 m: it covers image columns u < cx.
    T, roi, plain = _setup(scene, fast)
    wall = [("wall", se3.make_pose(np.eye(3), [-0.1, 0.0, 0.35]))]
    masks = fast.render_masks("cube", T, scene.camera, roi, occluders=wall)
    roi_cam = roi.camera(scene.camera)
    hidden = np.arange(roi.shape[1]) < roi_cam.cx  # columns behind the wall
    np.testing.assert_array_equal(masks[:, :, ~hidden], plain[:, :, ~hidden])
    assert not masks[:, :, hidden].any()
    assert plain[:, :, hidden].any()  # the object did reach behind the wall


def test_occluders_combine_and_score(scene, fast):
    T, roi, plain = _setup(scene, fast)
    left = ("wall", se3.make_pose(np.eye(3), [-0.1, 0.0, 0.35]))
    right = ("wall", se3.make_pose(np.eye(3), [0.1 + 0.004, 0.0, 0.4]))
    both = fast.render_masks("cube", T, scene.camera, roi, occluders=[left, right])
    one = fast.render_masks("cube", T, scene.camera, roi, occluders=[left])
    assert not (both & ~one).any() and both.sum() < one.sum()
    observed = both[0]
    scores = fast.score_masks("cube", T, scene.camera, roi, observed, occluders=[left, right])
    assert scores[0] == 1.0 and (scores[1:] < 1.0).all()


def test_scores_follow_a_replaced_occluder_mesh(scene):
    # Scoring keeps each occluder's threshold map per pose and window; registering the mesh
    # anew must drop it, or the old occluder would keep hiding the object.
    r = NumbaMaskRenderer()
    r.add_mesh("cube", scene.cube().vertices, scene.cube().faces)
    big = trimesh.creation.box((0.2, 0.2, 0.002))
    r.add_mesh("occ", big.vertices, big.faces)
    T = scene.camera_particles(np.random.default_rng(5), 6, 0.45, spread_m=0.002)
    roi = roi_for_particles(r.mesh("cube"), T, scene.camera)
    occ = [("occ", se3.make_pose(np.eye(3), [-0.1, 0.0, 0.35]))]
    observed = r.render_masks("cube", T[:1], scene.camera, roi)[0]
    hidden = r.score_masks("cube", T, scene.camera, roi, observed, occluders=occ)
    small = trimesh.creation.box((0.001, 0.001, 0.001))
    r.add_mesh("occ", small.vertices, small.faces)
    shown = r.score_masks("cube", T, scene.camera, roi, observed, occluders=occ)
    assert shown[0] == 1.0 and hidden[0] < 0.95  # the half wall hid part of the pose observed
    np.testing.assert_array_equal(shown, r.score_masks("cube", T, scene.camera, roi, observed))


def _left_half(scene) -> np.ndarray:
    """Image columns left of the principal point, as a full-image pixel occluder mask."""
    cols = np.arange(scene.camera.width) < scene.camera.cx
    return np.broadcast_to(cols, (scene.camera.height, scene.camera.width)).copy()


def test_pixel_occluder_hides_its_pixels_from_masks_depth_and_scores(scene, fast):
    T, roi, plain = _setup(scene, fast)
    hidden = roi.crop(_left_half(scene))
    occ = [(PIXEL_OCCLUDER, _left_half(scene))]
    masks = fast.render_masks("cube", T, scene.camera, roi, occluders=occ)
    np.testing.assert_array_equal(masks, plain & ~hidden)
    assert plain[:, hidden].any()  # the poses did reach into the hidden pixels
    depth = fast.render_depth("cube", T, scene.camera, roi, occluders=occ)
    assert np.isinf(depth[:, hidden]).all() and np.isfinite(depth[:, ~hidden][plain[:, ~hidden]]).all()
    # scored as the pixels outside it alone: the same as scoring the cleared masks without it
    observed = plain[0] & ~hidden
    np.testing.assert_allclose(
        fast.score_masks("cube", T, scene.camera, roi, observed, occluders=occ),
        iou_scores(plain & ~hidden, observed))


def test_pixel_occluder_combines_with_a_mesh_and_agrees_with_pyrender(scene, fast, reference):
    T, roi, _ = _setup(scene, fast)
    wall = ("wall", se3.make_pose(np.eye(3), [0.1 + 0.004, 0.0, 0.4]))
    occ = [wall, (PIXEL_OCCLUDER, _left_half(scene))]
    a = fast.render_masks("cube", T, scene.camera, roi, occluders=occ)
    b = reference.render_masks("cube", T, scene.camera, roi, occluders=occ)
    mesh_only = fast.render_masks("cube", T, scene.camera, roi, occluders=[wall])
    np.testing.assert_array_equal(a, mesh_only & ~roi.crop(_left_half(scene)))
    assert (a == b).mean() > 0.99


def test_pixel_occluder_of_the_wrong_shape_is_refused(scene, fast):
    T, roi, _ = _setup(scene, fast)
    with pytest.raises(ValueError, match=r"pixel occluder must be a \(480, 640\) bool image mask, got bool \(10, 10\)"):
        fast.render_masks("cube", T, scene.camera, roi, occluders=[(PIXEL_OCCLUDER, np.zeros((10, 10), bool))])
