"""Batched rendering equals a loop over single poses, is deterministic, and checks its inputs."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from numba import get_num_threads, set_num_threads

from mvtop_cli.errors import MeshError
from mvtop_cli.render import NumbaMaskRenderer, Roi, roi_for_particles


@pytest.mark.parametrize("mode", ["silhouette", "tactile"])
def test_batched_equals_looped(scene, fast, mode):
    rng = np.random.default_rng(12)
    if mode == "silhouette":
        cam = scene.camera
        T = scene.camera_particles(rng, 33, 0.35)
        kw = {}
    else:
        cam = scene.tactile
        T = scene.pressed_poses(rng, fast.mesh("connector").vertices, 33)
        kw = dict(mode="tactile", gel_distance_m=scene.gel_distance_m)
    roi = roi_for_particles(fast.mesh("connector"), T, cam, **kw)
    batched = fast.render_masks("connector", T, cam, roi, **kw)
    looped = np.stack([fast.render_masks("connector", T[i], cam, roi, **kw)[0] for i in range(len(T))])
    np.testing.assert_array_equal(batched, looped)
    observed = batched[5]
    scores = fast.score_masks("connector", T, cam, roi, observed, **kw)
    one_by_one = [fast.score_masks("connector", T[i], cam, roi, observed, **kw)[0] for i in range(len(T))]
    np.testing.assert_array_equal(scores, one_by_one)
    assert scores[5] == 1.0


def test_deterministic_across_calls_and_threads(scene, fast):
    rng = np.random.default_rng(13)
    T = scene.camera_particles(rng, 200, 0.5)
    roi = roi_for_particles(fast.mesh("cube"), T, scene.camera)
    first = fast.render_masks("cube", T, scene.camera, roi)
    depth = fast.render_depth("cube", T, scene.camera, roi)
    threads = get_num_threads()
    try:
        set_num_threads(1)
        np.testing.assert_array_equal(fast.render_masks("cube", T, scene.camera, roi), first)
        np.testing.assert_array_equal(fast.render_depth("cube", T, scene.camera, roi), depth)
    finally:
        set_num_threads(threads)
    np.testing.assert_array_equal(fast.render_masks("cube", T, scene.camera, roi), first)


def test_culling_does_not_change_masks(scene):
    # The same cube with inward winding is not "closed", so it is drawn without culling.
    box = scene.cube()
    renderer = NumbaMaskRenderer()
    renderer.add_mesh("out", box.vertices, box.faces)
    renderer.add_mesh("in", box.vertices, box.faces[:, ::-1])
    assert renderer.mesh("out").closed and not renderer.mesh("in").closed
    rng = np.random.default_rng(14)
    T = scene.camera_particles(rng, 50, 0.3)
    roi = roi_for_particles(renderer.mesh("out"), T, scene.camera)
    np.testing.assert_array_equal(
        renderer.render_masks("out", T, scene.camera, roi), renderer.render_masks("in", T, scene.camera, roi)
    )
    np.testing.assert_array_equal(
        renderer.render_depth("out", T, scene.camera, roi), renderer.render_depth("in", T, scene.camera, roi)
    )


def test_masks_have_no_holes_on_shared_edges(scene):
    # A fan of thin triangles whose shared edges run through pixel centres: a filled disc.
    n = 720
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    v = np.vstack([[0.0, 0.0, 0.0], np.column_stack([0.02 * np.cos(a), 0.02 * np.sin(a), np.zeros(n)])])
    f = np.column_stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n])
    renderer = NumbaMaskRenderer()
    renderer.add_mesh("disc", v, f)
    cam = scene.camera
    # Put the fan's centre exactly on a pixel centre.
    T = np.eye(4)
    T[:3, 3] = [(300 - cam.cx) / cam.fx * 0.4, (200 - cam.cy) / cam.fy * 0.4, 0.4]
    m = renderer.render_masks("disc", T, cam, Roi.full(cam))[0]
    yy, xx = np.mgrid[:480, :640]
    inner = (xx - 300) ** 2 + (yy - 200) ** 2 < (0.02 * cam.fx / 0.4 - 1.5) ** 2
    assert m[inner].all()


def test_bad_inputs_are_reported(scene, fast):
    roi = Roi.full(scene.camera)
    with pytest.raises(MeshError, match="'nope' is not registered"):
        fast.render_masks("nope", np.eye(4), scene.camera, roi)
    with pytest.raises(ValueError, match="gel_distance_m"):
        fast.render_masks("cube", np.eye(4), scene.camera, roi, mode="tactile")
    with pytest.raises(ValueError, match="render mode"):
        fast.render_masks("cube", np.eye(4), scene.camera, roi, mode="depth")
    with pytest.raises(ValueError, match="T_sensor_object"):
        fast.render_masks("cube", np.eye(3), scene.camera, roi)
    with pytest.raises(ValueError, match="observed mask shape"):
        fast.score_masks("cube", np.eye(4), scene.camera, roi, np.zeros((4, 4), bool))
    with pytest.raises(MeshError, match="face indices"):
        fast.add_mesh("broken", np.zeros((3, 3)), np.array([[0, 1, 3]]))
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    with pytest.raises(MeshError, match="non-finite"):
        fast.add_mesh("nan", np.where(np.arange(3) == 0, np.nan, box.vertices), box.faces)
    assert fast.render_masks("cube", np.zeros((0, 4, 4)), scene.camera, roi).shape == (0, 480, 640)
