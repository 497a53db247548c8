"""The numba renderer agrees with the pyrender reference on masks and depths."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.geometry import se3
from mvtop_cli.render import Roi, iou_scores, roi_for_particles


def _pairwise_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([iou_scores(a[i : i + 1], b[i])[0] for i in range(len(a))])


@pytest.mark.parametrize("mesh_id", ["cube", "connector"])
@pytest.mark.parametrize("distance_m", [0.3, 0.45, 0.6])
def test_camera_masks_agree_with_pyrender(scene, fast, reference, mesh_id, distance_m):
    rng = np.random.default_rng(int(distance_m * 100) + len(mesh_id))
    T = scene.camera_particles(rng, 12, distance_m, spread_m=0.008)
    roi = roi_for_particles(fast.mesh(mesh_id), T, scene.camera, max_side=112)
    assert 30 <= max(roi.shape) <= 112
    a = fast.render_masks(mesh_id, T, scene.camera, roi)
    b = reference.render_masks(mesh_id, T, scene.camera, roi)
    assert b.any(axis=(1, 2)).all()
    iou = _pairwise_iou(a, b)
    assert iou.mean() >= 0.97, iou
    assert iou.min() >= 0.9, iou


# The 25 mm cube is larger than the sensor's 19 x 14 mm view: held nearly flat its contact
# stays in view; the connector can tilt more.
@pytest.mark.parametrize("mesh_id, max_tilt_rad", [("cube", 0.01), ("connector", 0.15)])
def test_tactile_masks_agree_with_pyrender(scene, fast, reference, mesh_id, max_tilt_rad):
    rng = np.random.default_rng(7)
    T = scene.pressed_poses(rng, fast.mesh(mesh_id).vertices, 16, max_tilt_rad=max_tilt_rad)
    roi = roi_for_particles(fast.mesh(mesh_id), T, scene.tactile, mode="tactile", gel_distance_m=scene.gel_distance_m)
    kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m, penetration_threshold_m=2e-5)
    a = fast.render_masks(mesh_id, T, scene.tactile, roi, **kw)
    b = reference.render_masks(mesh_id, T, scene.tactile, roi, **kw)
    assert b.any(axis=(1, 2)).all()
    iou = _pairwise_iou(a, b)
    assert iou.mean() >= 0.97, iou


def test_tactile_depth_agrees_with_pyrender(scene, fast, reference):
    rng = np.random.default_rng(3)
    T = scene.pressed_poses(rng, fast.mesh("cube").vertices, 6, max_tilt_rad=0.02)
    roi = Roi.full(scene.tactile)
    a = fast.render_depth("cube", T, scene.tactile, roi)
    b = reference.render_depth("cube", T, scene.tactile, roi)
    both = np.isfinite(a) & np.isfinite(b)
    assert both.sum() > 0.98 * np.isfinite(b).sum()
    np.testing.assert_allclose(a[both], b[both], atol=2e-6)


def test_occluded_masks_agree_with_pyrender(scene, fast, reference):
    rng = np.random.default_rng(11)
    T = scene.camera_particles(rng, 10, 0.45)
    # The edge of a wall 10 cm nearer to the camera crosses the object's view.
    occ = [("wall", se3.make_pose(np.eye(3), [0.11, 0.0, 0.35]))]
    roi = roi_for_particles(fast.mesh("cube"), T, scene.camera)
    a = fast.render_masks("cube", T, scene.camera, roi, occluders=occ)
    b = reference.render_masks("cube", T, scene.camera, roi, occluders=occ)
    full = fast.render_masks("cube", T, scene.camera, roi)
    assert (a.sum(axis=(1, 2)) < full.sum(axis=(1, 2))).all()  # the wall hides part of each
    assert a.any(axis=(1, 2)).all()
    assert _pairwise_iou(a, b).mean() >= 0.97


def test_near_plane_clipping_agrees_with_pyrender(scene, fast, reference):
    # The 1 mm near plane cuts these cubes open; through the cut both renderers see the
    # inside faces (the numba renderer stops culling back faces for such poses).
    T = np.stack(
        [
            se3.make_pose(np.eye(3), [0.0, 0.0, 0.006]),  # the camera inside the cube
            se3.make_pose(se3.rotvec_to_matrix([0.3, 0.2, 0.1]), [0.016, 0.004, 0.008]),
        ]
    )
    roi = Roi(0, 0, 640, 480, 0.25)
    a = fast.render_masks("cube", T, scene.camera, roi)
    b = reference.render_masks("cube", T, scene.camera, roi)
    assert a[0].all() and 0.2 < a[1].mean() < 0.9
    assert (_pairwise_iou(a, b) > 0.99).all()
    da = fast.render_depth("cube", T, scene.camera, roi)
    db = reference.render_depth("cube", T, scene.camera, roi)
    both = np.isfinite(da) & np.isfinite(db)
    np.testing.assert_allclose(da[both], db[both], atol=2e-6)


def test_both_renderers_sample_pixel_centres(scene, fast, reference):
    # A square facing the camera spanning u in [10.3, 20.7], v in [5.3, 15.7]: pixels are
    # in when their centre (u, v) = (column, row) is, i.e. columns 11..20 and rows 6..15.
    cam = scene.camera
    z = 0.5
    corners_uv = [(10.3, 5.3), (20.7, 5.3), (20.7, 15.7), (10.3, 15.7)]
    v = np.array([[(u - cam.cx) / cam.fx * z, (w - cam.cy) / cam.fy * z, z] for u, w in corners_uv])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    for renderer in (fast, reference):
        renderer.add_mesh("square", v, f)
        m = renderer.render_masks("square", np.eye(4), cam, Roi(0, 0, 64, 32))[0]
        ys, xs = np.nonzero(m)
        assert (xs.min(), xs.max(), ys.min(), ys.max()) == (11, 20, 6, 15), type(renderer).__name__
        assert m.sum() == 100
