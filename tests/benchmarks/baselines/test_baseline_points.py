"""Observations as labelled point sets: surface points lie on the object, free points outside it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from mvtop_cli.benchmarks.baselines.points import (
    FREE,
    SURFACE,
    LabelledPoints,
    back_project,
    camera_free_points,
    environment_free_points,
    tactile_points,
)
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera

ROOT = Path(__file__).resolve().parents[3]


def sphere_depth(camera: PinholeCamera, centre: np.ndarray, radius: float) -> np.ndarray:
    """(H, W) z depth [m] of the nearest intersection of each pixel's ray with a sphere (inf: none)."""
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    d = back_project(camera, cols.ravel(), rows.ravel(), np.ones(rows.size))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tc = d @ centre
    disc = radius**2 - (centre @ centre - tc**2)
    t = np.where(disc >= 0, tc - np.sqrt(np.maximum(disc, 0)), np.inf)
    return (t * d[:, 2]).reshape(camera.height, camera.width)


@pytest.fixture
def tactile_camera() -> PinholeCamera:
    return PinholeCamera.from_fov(160, 120, fx=160 / 0.0186 * 0.025)  # an 18.6 mm pad 25 mm away


def test_tactile_points_lie_on_the_pressing_sphere_and_free_points_outside(tactile_camera):
    gel = 0.025
    centre, radius = np.array([0.001, -0.0005, gel + 0.004 - 0.0006]), 0.004  # pressed 0.6 mm into the gel
    z = sphere_depth(tactile_camera, centre, radius)
    indentation = np.clip(gel - z, 0.0, None)
    pts = tactile_points(indentation, tactile_camera, gel, stride_px=1)
    surface, free = pts.surface, pts.free
    # the contact disc: radius sqrt(r^2 - (r - 0.6 mm)^2) = 2.08 mm, ~0.116 mm per pixel
    assert 800 < len(surface) < 1300
    np.testing.assert_allclose(np.linalg.norm(surface - centre, axis=1), radius, atol=1e-9)
    assert np.all(surface[:, 2] <= gel)
    assert len(free) == 2 * tactile_camera.width * tactile_camera.height  # two layers behind every pixel
    assert np.all(np.linalg.norm(free - centre, axis=1) > radius)
    # behind the gel surface: 0.5 and 1 mm closer to the camera than the (pressed) surface
    np.testing.assert_allclose(np.sort(np.unique(np.round(gel - free[:, 2], 9)))[:1], [5e-4])


def test_tactile_points_move_with_the_sensor_pose(tactile_camera):
    rng = np.random.default_rng(3)
    gel = 0.025
    centre, radius = np.array([0.0, 0.0, gel + 0.003 - 0.0004]), 0.003
    pts = tactile_points(np.clip(gel - sphere_depth(tactile_camera, centre, radius), 0, None), tactile_camera, gel)
    T_ee_sensor = se3.exp_se3(np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 1.0, 3)]))
    moved = pts.transformed(T_ee_sensor)
    c_ee = se3.transform_points(T_ee_sensor, centre[None])[0]
    np.testing.assert_allclose(np.linalg.norm(moved.surface - c_ee, axis=1), radius, atol=1e-9)
    assert np.all(np.linalg.norm(moved.free - c_ee, axis=1) > radius)
    np.testing.assert_array_equal(moved.labels, pts.labels)


def test_no_contact_gives_only_free_points(tactile_camera):
    pts = tactile_points(np.zeros((120, 160)), tactile_camera, 0.025, stride_px=4)
    assert len(pts.surface) == 0 and len(pts.free) == 2 * 30 * 40
    with pytest.raises(ValueError, match="does not match the camera"):
        tactile_points(np.zeros((10, 10)), tactile_camera, 0.025)


def test_camera_carving_stays_outside_the_object_and_in_front_of_occluders():
    cam = PinholeCamera.from_fov(320, 240, fx=300.0)
    centre, radius = np.array([0.002, 0.001, 0.3]), 0.01
    mask = np.isfinite(sphere_depth(cam, centre, radius))
    wall = np.full(mask.shape, np.inf)
    wall[:, 200:] = 0.302  # an occluder covering the right part of the image, through the sphere's far half
    region = 0.02
    pts = camera_free_points(mask, cam, centre, region, occluder_depth_m=wall, spacing_m=5e-4, stride_px=1,
                             mask_margin_px=1, occluder_margin_m=1e-3)
    free = pts.free
    assert len(free) > 1000 and len(pts.surface) == 0
    dist = np.linalg.norm(free - centre, axis=1)
    assert np.all(dist > radius) and np.all(dist <= region + 1e-9)
    # carving reaches close to the object: within a pixel (1 mm at 0.3 m) plus a sample spacing
    assert dist.min() < radius + 1.6e-3
    u = cam.project(free)[:, 0]
    behind_wall = (np.round(u) >= 200) & (free[:, 2] > 0.302 - 1e-3)
    assert not behind_wall.any()
    assert np.any((np.round(u) < 200) & (free[:, 2] > 0.302))  # left of the wall the rays run on


def test_environment_points_lie_inside_the_solid():
    # the environment: the half-space z < 0 (a table), signed distance z
    pts = environment_free_points(lambda p: p[:, 2], np.array([0.0, 0.0, 0.005]), 0.01, spacing_m=1e-3, margin_m=2.5e-4)
    free = pts.free
    assert len(free) > 100 and np.all(pts.labels == FREE)
    assert np.all(free[:, 2] < -2.5e-4)
    assert np.all(np.linalg.norm(free - [0.0, 0.0, 0.005], axis=1) <= 0.01 + 1e-12)
    np.testing.assert_allclose(free / 1e-3, np.round(free / 1e-3), atol=1e-9)  # on the lattice


def test_downsampling_keeps_one_mean_point_per_label_and_voxel():
    p = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [0.2, 0.2, 0.2], [1.5, 0.2, 0.2]]) * 1e-3
    pts = LabelledPoints(p, [SURFACE, SURFACE, FREE, FREE])
    d = pts.downsampled(1e-3)
    np.testing.assert_allclose(d.surface, [[0.2e-3, 0.2e-3, 0.2e-3]])
    np.testing.assert_allclose(d.free, [[0.2e-3, 0.2e-3, 0.2e-3], [1.5e-3, 0.2e-3, 0.2e-3]])
    again = LabelledPoints(p[::-1], [FREE, FREE, SURFACE, SURFACE]).downsampled(1e-3)
    np.testing.assert_allclose(again.points, d.points)  # the order of the input does not matter
    with pytest.raises(ValueError, match="labels must be"):
        LabelledPoints(p, [0, 1, 2, 0])


@pytest.mark.slow
def test_points_of_a_sample_log_agree_with_the_ground_truth():
    from mvtop_cli.benchmarks.baselines.observations import PointOptions, log_points
    from mvtop_cli.config import load_config

    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    lp = log_points(ROOT / "sample_logs" / "conn2.mcap", cfg, PointOptions(last_frames=2), max_frames=20)
    assert lp.frames_used == 2 and lp.last_index == 19
    T_obj_ee = se3.invert(se3.invert(lp.T_world_ee) @ lp.T_world_object_gt)
    mesh = trimesh.load(ROOT / "configs" / "meshes" / "conn2.obj", force="mesh")
    surface = se3.transform_points(T_obj_ee, lp.points.surface)
    free = se3.transform_points(T_obj_ee, lp.points.free)
    assert len(surface) > 100 and len(free) > 1000
    d_surface = np.abs(trimesh.proximity.signed_distance(mesh, surface))
    assert np.median(d_surface) < 1e-4 and d_surface.max() < 3e-4  # the gel's 1 um depth steps, pixel and voxel size
    inside = trimesh.proximity.signed_distance(mesh, free)  # positive inside the mesh
    assert np.mean(inside > 0) < 1e-3 and inside.max() < 1e-3


def test_missing_extra_stops_the_benchmark_before_any_run_with_the_pip_command(tmp_path, monkeypatch):
    from mvtop_cli.benchmarks.accuracy import AccuracyOptions, run_accuracy
    from mvtop_cli.benchmarks.baselines.chsel_runner import BaselineUnavailable, available

    monkeypatch.setitem(__import__("sys").modules, "chsel", None)  # as if chsel were not installed
    assert not available()
    out = tmp_path / "bench"
    with pytest.raises(BaselineUnavailable) as err:
        run_accuracy(out, AccuracyOptions(objects=("conn2",), poses=1, methods=("M-TOP", "CHSEL")))
    msg = str(err.value)
    assert "\n" not in msg and "pip install" in msg and "chsel" in msg
    assert not out.exists()  # nothing was written
