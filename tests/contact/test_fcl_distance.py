"""FclDistance: exact surface distance for separated poses, 0 when colliding."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.contact.fcl_distance import FclDistance
from mvtop_cli.errors import MeshError
from mvtop_cli.geometry import se3

MM = 1e-3


def test_gap_to_floor_is_exact(geo, cube_fcl):
    for gap in (1e-6, 0.2 * MM, 4 * MM):
        assert cube_fcl.distance(geo.translation(z=geo.FLOOR_Z + gap)) == pytest.approx(gap, abs=1e-12)


def test_colliding_gives_zero_not_depth(geo, cube_fcl):
    T = np.stack([geo.translation(z=geo.FLOOR_Z - 1 * MM), geo.translation(z=geo.FLOOR_Z)])
    d = cube_fcl.distance(T)
    np.testing.assert_array_equal(d, [0.0, 0.0])


def test_single_pose_gives_scalar(geo, cube_fcl):
    d = cube_fcl.distance(geo.translation(z=geo.BLOCK_H + 5 * MM))
    assert np.ndim(d) == 0


def test_batched_equals_looped(geo, cube_fcl):
    rng = np.random.default_rng(3)
    T = se3.make_pose(
        se3.rotvec_to_matrix(rng.normal(0.0, 0.3, (20, 3))),
        rng.uniform([-10 * MM, -10 * MM, geo.FLOOR_Z], [10 * MM, 10 * MM, geo.BLOCK_H], (20, 3)),
    )
    np.testing.assert_array_equal(cube_fcl.distance(T), [cube_fcl.distance(T_i) for T_i in T])


def test_environment_poses_and_several_meshes(geo):
    cube = trimesh.creation.box(extents=[10 * MM] * 3)  # centred
    wall = trimesh.creation.box(extents=[2 * MM, 50 * MM, 50 * MM])
    # two walls at x = +-20 mm (inner faces at +-19 mm)
    T_world_env = np.stack([geo.translation(x=20 * MM), geo.translation(x=-20 * MM)])
    fcl = FclDistance(cube, [wall, wall], T_world_env)
    assert fcl.distance(geo.translation(x=10 * MM)) == pytest.approx(4 * MM, abs=1e-12)
    assert fcl.distance(geo.translation(x=-12 * MM)) == pytest.approx(2 * MM, abs=1e-12)
    assert fcl.distance(np.eye(4)) == pytest.approx(14 * MM, abs=1e-12)


def test_bad_inputs_rejected(cube_mesh):
    with pytest.raises(MeshError, match="no environment meshes"):
        FclDistance(cube_mesh, [])
    with pytest.raises(ValueError, match="poses"):
        FclDistance(cube_mesh, [cube_mesh], np.stack([np.eye(4)] * 2))
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(MeshError, match="environment mesh 0"):
        FclDistance(cube_mesh, [empty])
