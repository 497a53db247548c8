"""The simulator's camera renders sample pixels where the estimator's renderer and camera_info
(OpenCV: pixel centres at integers) say they are; the recorded true masks are exact."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render.numba_renderer import NumbaMaskRenderer
from mvtop_cli.render.roi import Roi
from mvtop_cli.sim.camera_render import CameraSceneRenderer, Material

CAMERA = PinholeCamera(640, 480, np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]]))


def _pose(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


@pytest.fixture(scope="module")
def scene():
    plate = trimesh.creation.box([0.02, 0.02, 0.001])  # 20 mm square facing the camera
    screen = trimesh.creation.box([0.01, 0.04, 0.001])
    renderer = CameraSceneRenderer({"object": (plate, Material((1.0, 1.0, 1.0))),
                                    "screen": (screen, Material((0.2, 0.2, 0.2)))}, CAMERA.width, CAMERA.height)
    # off-centre by a third of a pixel in u: pixel-centre sampling decides which column is covered
    T_plate = _pose(0.0013, 0.0021, 0.3)
    renderer.set_pose("object", T_plate)
    renderer.set_pose("screen", _pose(0.012, 0.0, 0.25))  # covers the plate's right-hand strip
    reference = NumbaMaskRenderer()
    reference.add_mesh("plate", plate.vertices, plate.faces)
    expected = reference.render_masks("plate", T_plate[None], CAMERA, Roi.full(CAMERA), [])[0]
    yield renderer, expected
    renderer.close()


def test_depth_of_one_mesh_covers_the_pixel_centres_the_estimator_renders(scene):
    renderer, expected = scene
    depth = renderer.render_depth_only(CAMERA, np.eye(4), only="object")
    covered = depth > 0
    assert covered.sum() == expected.sum() > 1000  # 33 x 34 px
    assert np.array_equal(covered, expected)  # was shifted by about (-0.1, +0.4) px before
    np.testing.assert_allclose(depth[covered], 0.3 - 0.0005, atol=2e-6)


def test_visible_mask_is_the_unoccluded_part_at_pixel_centres(scene):
    renderer, expected = scene
    mask = renderer.visible_mask(CAMERA, np.eye(4), only="object")
    # the screen at 0.25 m spans u >= 500 * 0.007 / 0.25 + 319.5 = 333.5
    cols = np.arange(CAMERA.width)
    np.testing.assert_array_equal(mask[:, cols < 333], expected[:, cols < 333])
    assert not mask[:, cols > 334].any() and expected[:, cols > 334].any()
