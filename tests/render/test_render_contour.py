"""The projected contour scored against image gradients (``render.contour``): the mesh's edge
topology, a sub-pixel peak at the pose that drew the image, occluders and bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from mvtop_cli.estimator.edges import image_gradients
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render import NumbaMaskRenderer
from mvtop_cli.render.base import PIXEL_OCCLUDER
from mvtop_cli.render.contour import ContourTopology, contour_gradient
from mvtop_cli.render.mesh import RenderMesh
from mvtop_cli.render.roi import Roi

# A 640x480 camera (the render tests' conftest has one too; fixtures cannot be module constants).
CAMERA = PinholeCamera(
    width=640, height=480, K=np.array([[615.4, 0.0, 322.1], [0.0, 614.8, 238.7], [0.0, 0.0, 1.0]])
)
SUPERSAMPLE = 8
T_CUBE = se3.make_pose(se3.rotvec_to_matrix(np.array([[0.3, -0.2, 0.1]]))[0], np.array([0.004, -0.002, 0.3]))


def _supersampled(camera: PinholeCamera, k: int) -> PinholeCamera:
    """The camera with ``k`` x ``k`` pixels for each of its pixels (same pixel-centre convention)."""
    K = camera.K.copy()
    K[:2, :2] *= k
    K[:2, 2] = (K[:2, 2] + 0.5) * k - 0.5
    return PinholeCamera(camera.width * k, camera.height * k, K)


def _image_of(renderer: NumbaMaskRenderer, T: np.ndarray, occluders=()) -> np.ndarray:
    """An anti-aliased RGB image of the cube at ``T``: dark object on a light background,
    each pixel's shade its covered fraction (8 x 8 samples)."""
    big = _supersampled(CAMERA, SUPERSAMPLE)
    m = renderer.render_masks("cube", T[None], big, Roi.full(big), list(occluders))[0].astype(np.float32)
    cover = cv2.resize(m, (CAMERA.width, CAMERA.height), interpolation=cv2.INTER_AREA)
    grey = (200.0 - 150.0 * cover).round().astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


@pytest.fixture(scope="module")
def renderer():
    r = NumbaMaskRenderer()
    r.add_mesh("cube", *(lambda b: (b.vertices, b.faces))(trimesh.creation.box((0.02, 0.02, 0.02))))
    r.add_mesh("wall", *(lambda b: (b.vertices, b.faces))(trimesh.creation.box((0.2, 0.2, 0.001))))
    return r


def _score(renderer, T, image, roi=None, occluders=None):
    """Mean gradient across the visible contour (0 where none is visible)."""
    gx, gy = image_gradients(image, 0.8)
    total, count = renderer.contour_gradient("cube", T, CAMERA, roi or Roi.full(CAMERA), gx, gy, occluders)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0)


def test_topology_of_a_closed_box():
    box = trimesh.creation.box((0.02, 0.02, 0.02))
    topo = ContourTopology.from_mesh(RenderMesh.from_trimesh(box))
    assert topo.edges.shape == (18, 2)  # 12 triangles: 12 box edges and 6 face diagonals
    assert (topo.edge_faces >= 0).all()  # closed: every edge has two faces
    assert topo.crease.sum() == 12  # the box's edges meet at 90 deg, its face diagonals at 0
    for (a, b), faces, opp in zip(topo.edges, topo.edge_faces, topo.opposite):
        for f, o in zip(faces, opp):
            tri = set(box.faces[f])
            assert {a, b} <= tri and tri - {a, b} == {o}


def test_edges_inside_the_hull_are_left_out():
    """A closed box with a closed box-shaped void inside: only the outer shell's edges are used
    (the void's contour edges are always hidden behind the outer shell)."""
    outer = trimesh.creation.box((0.02, 0.02, 0.02))
    inner = trimesh.creation.box((0.01, 0.01, 0.01))
    inner.invert()
    both = trimesh.util.concatenate([outer, inner])
    topo = ContourTopology.from_mesh(RenderMesh.from_trimesh(both))
    assert topo.edges.shape == (18, 2)
    assert topo.edges.max() < len(outer.vertices)  # the outer shell's vertices come first


def test_the_pose_that_drew_the_image_scores_highest_to_a_fraction_of_a_pixel(renderer):
    image = _image_of(renderer, T_CUBE)
    steps_m = np.linspace(-3e-4, 3e-4, 7)  # 0.1 mm = 0.2 px at 0.3 m
    for axis in range(2):  # across the optical axis (0.3 mm along it changes the outline by 0.02 px)
        dt = np.zeros((len(steps_m), 3))
        dt[:, axis] = steps_m
        T = se3.perturb_about_origin(np.repeat(T_CUBE[None], len(steps_m), 0), dt, np.zeros_like(dt))
        s = _score(renderer, T, image)
        assert np.argmax(s) == 3, (axis, s)
        # parabola through the three best: the peak within 0.03 mm (0.06 px) of the truth
        a, b, c = s[2:5]
        peak_m = 0.5 * (a - c) / (a - 2 * b + c) * 1e-4
        assert abs(peak_m) < 3e-5, (axis, peak_m)
    # the outline of a 150-level step: the mean gradient across it is a sizeable fraction of that
    assert 20.0 < _score(renderer, T_CUBE[None], image)[0] < 150.0


def test_a_featureless_image_scores_zero(renderer):
    flat = np.full((CAMERA.height, CAMERA.width, 3), 120, np.uint8)
    np.testing.assert_array_equal(_score(renderer, T_CUBE[None], flat), [0.0])


def test_contour_behind_an_occluder_is_not_read(renderer):
    image = _image_of(renderer, T_CUBE)
    wall_in_front = [("wall", se3.make_pose(np.eye(3), [0.0, 0.0, 0.2]))]
    wall_behind = [("wall", se3.make_pose(np.eye(3), [0.0, 0.0, 0.5]))]
    np.testing.assert_array_equal(_score(renderer, T_CUBE[None], image, occluders=wall_in_front), [0.0])
    np.testing.assert_allclose(_score(renderer, T_CUBE[None], image, occluders=wall_behind),
                               _score(renderer, T_CUBE[None], image), rtol=0, atol=1e-12)


def test_contour_along_an_occluder_outline_is_not_read(renderer):
    """A wall in front whose edge runs 1.5 px beside the cube's left outline hides nothing, but
    with a 3 px margin the samples of that outline are skipped (they would read the wall's edge;
    the wall's outline is where the occluders' inverse depth steps by more than 1 %)."""
    T = se3.make_pose(np.eye(3), [0.004, -0.002, 0.3])[None]  # face-on: a square outline
    image = _image_of(renderer, T[0])
    gx, gy = image_gradients(image, 0.8)
    u_left = CAMERA.fx * (0.004 - 0.01) / 0.29 + CAMERA.cx  # the front face is at z = 0.29 m
    x_wall = ((u_left - 1.5) - CAMERA.cx) * 0.2 / CAMERA.fx - 0.1  # wall centre: its right edge 1.5 px left
    thr = renderer._threshold([("wall", se3.make_pose(np.eye(3), [x_wall, 0.0, 0.2]))], CAMERA, Roi.full(CAMERA), None)
    mesh = renderer.mesh("cube")
    topo = ContourTopology.from_mesh(mesh)
    counts = [contour_gradient(mesh, topo, T, CAMERA, Roi.full(CAMERA), gx, gy, t, 1.0, m, 0.01, 0.01)[1][0]
              for t, m in ((None, 0.0), (thr, 0.0), (thr, 3.0))]
    side_px = CAMERA.fy * 0.02 / 0.29  # the left outline's length
    assert counts[0] == counts[1], counts
    assert abs((counts[1] - counts[2]) - side_px) <= 3, (counts, side_px)
    # a pixel occluder over the same columns: its edge is an outline as the wall's is
    hidden = np.broadcast_to(np.arange(CAMERA.width) < round(u_left - 1.5), (CAMERA.height, CAMERA.width)).copy()
    thr = renderer._threshold([(PIXEL_OCCLUDER, hidden)], CAMERA, Roi.full(CAMERA), None)
    pixels = [contour_gradient(mesh, topo, T, CAMERA, Roi.full(CAMERA), gx, gy, thr, 1.0, m, 0.01, 0.01)[1][0]
              for m in (0.0, 3.0)]
    assert pixels[0] == counts[0], (pixels, counts)
    assert abs((pixels[0] - pixels[1]) - side_px) <= 3, (pixels, side_px)


def test_a_roi_window_scores_like_the_full_image(renderer):
    from mvtop_cli.estimator.edges import roi_gradients

    image = _image_of(renderer, T_CUBE)
    gx, gy = image_gradients(image, 0.8)
    roi = Roi(240, 160, 160, 160)
    T = se3.perturb_about_origin(np.repeat(T_CUBE[None], 3, 0), np.array([[0, 0, 0], [2e-4, 0, 0], [0, 3e-4, 0]]),
                                 np.zeros((3, 3)))
    full = renderer.contour_gradient("cube", T, CAMERA, Roi.full(CAMERA), gx, gy)
    win = renderer.contour_gradient("cube", T, CAMERA, roi, *roi_gradients(gx, gy, roi))
    np.testing.assert_allclose(win[0], full[0], rtol=1e-5)
    np.testing.assert_array_equal(win[1], full[1])


def test_gradients_of_the_wrong_size_are_refused(renderer):
    image = _image_of(renderer, T_CUBE)
    gx, gy = image_gradients(image, 0.8)
    with pytest.raises(ValueError, match=r"must be \(C, 100, 100\), the ROI's size"):
        renderer.contour_gradient("cube", T_CUBE[None], CAMERA, Roi(0, 0, 100, 100), gx, gy)
