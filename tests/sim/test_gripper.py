"""Tests for mvtop_cli.sim.gripper: finger meshes and poses, tactile camera, grasp fit."""

from __future__ import annotations

import fcl
import numpy as np
import pytest
import trimesh

from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.sim.gripper import (
    FINGERTIP_OFFSET_M,
    T_finger_tactile_optical,
    finger_poses,
    gripper_meshes,
    tactile_camera,
)
from mvtop_cli.sim.objects import get_object, list_objects

MM = 1e-3


def _fcl_object(mesh: trimesh.Trimesh, T: np.ndarray) -> fcl.CollisionObject:
    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.vertices), len(mesh.faces))
    bvh.addSubModel(mesh.vertices, mesh.faces)
    bvh.endModel()
    return fcl.CollisionObject(bvh, fcl.Transform(T[:3, :3], T[:3, 3]))


def collides(a: trimesh.Trimesh, T_a: np.ndarray, b: trimesh.Trimesh, T_b: np.ndarray) -> bool:
    """Whether the surfaces of ``a`` at pose ``T_a`` and ``b`` at ``T_b`` intersect."""
    request, result = fcl.CollisionRequest(), fcl.CollisionResult()
    return fcl.collide(_fcl_object(a, T_a), _fcl_object(b, T_b), request, result) > 0


# ----------------------------------------------------------------------------- finger poses


def test_finger_poses_place_pads_opening_apart_facing_each_other():
    opening = 0.0213
    poses = finger_poses(opening)
    left, right = poses["left"], poses["right"]
    for T in (left, right):
        R = T[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert T[0, 3] == 0.0 and T[2, 3] == 0.0  # pad centres on the ee y axis
    assert left[1, 3] == pytest.approx(opening / 2) and right[1, 3] == pytest.approx(-opening / 2)
    assert np.linalg.norm(left[:3, 3] - right[:3, 3]) == pytest.approx(opening)
    # pad normals (finger +z) point at each other; the fingertip (finger +y) is ee +z
    assert np.allclose(left[:3, 2], [0, -1, 0]) and np.allclose(right[:3, 2], [0, 1, 0])
    assert np.allclose(left[:3, 1], [0, 0, 1]) and np.allclose(right[:3, 1], [0, 0, 1])
    # the right finger is the left one turned half a turn about ee z
    Rz = np.diag([-1.0, -1.0, 1.0, 1.0])
    assert np.allclose(Rz @ left, right)


def test_finger_poses_batched_equal_looped():
    openings = np.random.default_rng(3).uniform(0.0, 0.1, size=(4, 3))
    batched = finger_poses(openings)
    for side in ("left", "right"):
        assert batched[side].shape == (4, 3, 4, 4)
        for idx in np.ndindex(openings.shape):
            assert np.array_equal(batched[side][idx], finger_poses(float(openings[idx]))[side])


@pytest.mark.parametrize("bad", [-1e-3, np.nan, np.inf])
def test_finger_poses_reject_bad_openings(bad):
    with pytest.raises(ValueError):
        finger_poses(bad)


def test_pad_gap_of_posed_meshes_is_the_opening():
    meshes = gripper_meshes()
    for opening in (0.0, 0.008, 0.05):
        poses = finger_poses(opening)
        left = trimesh.transform_points(meshes["left"].vertices, poses["left"])
        right = trimesh.transform_points(meshes["right"].vertices, poses["right"])
        # innermost surfaces (the gel pads) are exactly `opening` apart
        assert left[:, 1].min() - right[:, 1].max() == pytest.approx(opening, abs=1e-12)
        # the fingertips sit FINGERTIP_OFFSET_M below the TCP
        assert left[:, 2].max() == pytest.approx(FINGERTIP_OFFSET_M, abs=1e-12)
        if opening > 0:
            assert not collides(meshes["left"], poses["left"], meshes["right"], poses["right"])


# ----------------------------------------------------------------------------- finger mesh


def test_finger_mesh_is_a_clean_solid_with_gelsight_mini_sized_pad():
    meshes = gripper_meshes()
    mesh = meshes["left"]
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    assert mesh.euler_number == 2 and len(mesh.faces) < 5000
    # the pad: the faces on the plane z = 0, 18.6 x 14.3 mm and centred on the origin
    on_pad = mesh.vertices[np.abs(mesh.vertices[:, 2]) < 1e-12]
    assert mesh.vertices[:, 2].max() == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(np.ptp(on_pad[:, :2], axis=0), [18.6 * MM, 14.3 * MM])
    assert np.allclose(on_pad[:, :2].min(0) + on_pad[:, :2].max(0), 0.0, atol=1e-12)
    # the finger plate behind it: ~20 wide x 25 tall, 8 mm thick including the gel
    plate = mesh.section(plane_origin=[0, 0, -4 * MM], plane_normal=[0, 0, 1]).discrete
    assert len(plate) == 1
    assert np.allclose(np.ptp(plate[0][:, :2], axis=0), [22 * MM, 25 * MM])
    behind = mesh.section(plane_origin=[0, 0, -8.5 * MM], plane_normal=[0, 0, 1])
    assert behind is not None  # the sensor body continues behind the 8 mm plate
    # both fingers share the geometry but not the object: callers may edit their copy
    meshes["left"].apply_translation([1.0, 0.0, 0.0])
    assert np.array_equal(gripper_meshes()["left"].vertices, meshes["right"].vertices)


# ----------------------------------------------------------------------------- tactile camera


def test_tactile_optical_frame_sees_gel_plane_at_gel_distance():
    d = 0.021
    T_f_o = T_finger_tactile_optical(d)
    R = T_f_o[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    gel_points_f = np.array([[0.0, 0.0, 0.0], [9.3 * MM, 7.15 * MM, 0.0], [-5 * MM, 2 * MM, 0.0]])
    gel_points_o = se3.transform_points(se3.invert(T_f_o), gel_points_f)
    assert np.allclose(gel_points_o[:, 2], d)
    # optical z is the pad normal: toward the object
    assert np.allclose(T_f_o[:3, 2], [0, 0, 1])
    # the camera sits inside the finger's sensor body, behind the gel
    finger = gripper_meshes()["left"]
    lo, hi = finger.bounds
    assert np.all(T_f_o[:3, 3] > lo) and np.all(T_f_o[:3, 3] < hi)


def test_tactile_camera_images_the_whole_pad_at_gelsight_mini_resolution():
    for d in (0.018, 0.025, 0.03):
        cam = tactile_camera(d)
        assert isinstance(cam, PinholeCamera)
        assert (cam.width, cam.height) == (320, 240)
        # pad corners land on the image corners (pixel edges at -0.5 and size - 0.5)
        corners = np.array([[-9.3, -7.15, 0.0], [9.3, 7.15, 0.0]]) * MM
        corners_o = se3.transform_points(se3.invert(T_finger_tactile_optical(d)), corners)
        uv = cam.project(corners_o)
        assert np.allclose(uv, [[-0.5, -0.5], [319.5, 239.5]], atol=1e-9)
        # about 0.06 mm per pixel on the gel surface; image x runs along the pad's long side
        assert d / cam.fx == pytest.approx(18.6 * MM / 320)
        assert 0.055 * MM < d / cam.fx < 0.065 * MM and 0.055 * MM < d / cam.fy < 0.065 * MM
        T_o_f = se3.invert(T_finger_tactile_optical(d))
        along_long = cam.project(se3.transform_points(T_o_f, np.array([[5 * MM, 0.0, 0.0]])))
        assert along_long[0, 0] > cam.cx and along_long[0, 1] == pytest.approx(cam.cy)


@pytest.mark.parametrize("bad", [0.0, -0.01, np.nan])
def test_tactile_rejects_bad_gel_distance(bad):
    with pytest.raises(ValueError):
        tactile_camera(bad)
    with pytest.raises(ValueError):
        T_finger_tactile_optical(bad)


# ----------------------------------------------------------------------------- grasps


@pytest.mark.parametrize("name", list_objects())
def test_nominal_grasp_holds_the_body_and_clears_the_receptacle(name):
    spec = get_object(name)
    T_ee_obj = spec.grasp
    meshes = gripper_meshes()
    # object +z is ee -z, and the grasp is a proper rigid transform
    assert np.allclose(T_ee_obj[:3, 2], [0, 0, -1])
    assert np.allclose(T_ee_obj[:3, :3] @ T_ee_obj[:3, :3].T, np.eye(3))
    T_obj_ee = se3.invert(T_ee_obj)
    # the object's width along the finger axis at the TCP is the grasp width, and nothing on
    # the object is wider (the pads meet the body first)
    tcp_height = T_obj_ee[2, 3]
    loops = spec.mesh.section(plane_origin=[0, 0, tcp_height], plane_normal=[0, 0, 1]).discrete
    width = np.ptp(np.concatenate(loops)[:, 1])
    assert width == pytest.approx(spec.grasp_width_m, abs=1e-12)
    assert spec.mesh.extents[1] == pytest.approx(spec.grasp_width_m, abs=1e-12)
    # a slightly wider opening is clear of the object; a slightly narrower one squeezes it
    for side in ("left", "right"):
        open_ = finger_poses(spec.grasp_width_m + 0.2 * MM)[side]
        shut = finger_poses(spec.grasp_width_m - 0.2 * MM)[side]
        assert not collides(meshes[side], open_, spec.mesh, T_ee_obj)
        assert collides(meshes[side], shut, spec.mesh, T_ee_obj)
    # the pads press on the body, above the part that enters the receptacle
    pad_half_height = 14.3 * MM / 2
    assert tcp_height - pad_half_height > spec.insertion_depth_m
    assert tcp_height < spec.mesh.extents[2]
    # inserted, the fingers stay above the receptacle mouth
    T_rec_ee = spec.T_receptacle_object_inserted @ T_obj_ee
    for side in ("left", "right"):
        T_rec_finger = T_rec_ee @ finger_poses(spec.grasp_width_m)[side]
        lowest = trimesh.transform_points(meshes[side].vertices, T_rec_finger)[:, 2].min()
        assert lowest > 0.0
        assert not collides(meshes[side], T_rec_finger, spec.receptacle_mesh, np.eye(4))
