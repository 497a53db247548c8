"""Shared geometry for the contact tests: a block with a square pocket and a small cube.

Tests reach the constants and builders through the ``geo`` fixture (test modules cannot
import this file under ``--import-mode=importlib``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

MM = 1e-3
BLOCK = 40 * MM  # block side
BLOCK_H = 20 * MM  # block height, bottom at z = 0
POCKET = 25.6 * MM  # pocket side
POCKET_DEPTH = 10 * MM  # pocket floor at z = BLOCK_H - POCKET_DEPTH
FLOOR_Z = BLOCK_H - POCKET_DEPTH
CUBE = 10 * MM


def pocket_block() -> trimesh.Trimesh:
    """A BLOCK x BLOCK x BLOCK_H box (xy-centred, z from 0) with a POCKET-wide square pocket
    of depth POCKET_DEPTH in its top face, as one watertight mesh."""
    o, i = BLOCK / 2, POCKET / 2
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
    v = np.concatenate(
        [
            np.c_[square * o, np.zeros(4)],  # 0-3 outer bottom
            np.c_[square * o, np.full(4, BLOCK_H)],  # 4-7 outer top
            np.c_[square * i, np.full(4, BLOCK_H)],  # 8-11 pocket rim
            np.c_[square * i, np.full(4, FLOOR_Z)],  # 12-15 pocket floor
        ]
    )
    f = [[0, 2, 1], [0, 3, 2]]  # bottom, facing -z
    f += [[12, 13, 14], [12, 14, 15]]  # pocket floor, facing +z
    for a in range(4):
        b = (a + 1) % 4
        f += [[a, b, 4 + b], [a, 4 + b, 4 + a]]  # outer walls, facing out
        f += [[4 + a, 4 + b, 8 + b], [4 + a, 8 + b, 8 + a]]  # top rim
        f += [[8 + a, 8 + b, 12 + b], [8 + a, 12 + b, 12 + a]]  # pocket walls, facing in
    mesh = trimesh.Trimesh(v, np.array(f), process=True)
    assert mesh.is_watertight and mesh.volume > 0
    return mesh


def cube_object() -> trimesh.Trimesh:
    """A CUBE-sided cube in an object frame with the origin at the centre of its bottom
    face (the face that enters first), +z up."""
    return trimesh.creation.box(extents=[CUBE] * 3, transform=translation(z=CUBE / 2))


def translation(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


@pytest.fixture(scope="session")
def geo() -> SimpleNamespace:
    return SimpleNamespace(
        MM=MM, BLOCK=BLOCK, BLOCK_H=BLOCK_H, POCKET=POCKET, POCKET_DEPTH=POCKET_DEPTH,
        FLOOR_Z=FLOOR_Z, CUBE=CUBE,
        pocket_block=pocket_block, cube_object=cube_object, translation=translation,
    )  # fmt: skip


@pytest.fixture(scope="session")
def pocket_mesh() -> trimesh.Trimesh:
    return pocket_block()


@pytest.fixture(scope="session")
def cube_mesh() -> trimesh.Trimesh:
    return cube_object()


@pytest.fixture(scope="session")
def pocket_sdf(pocket_mesh):
    from mvtop_cli.contact.sdf import EnvironmentSDF

    margin = 5 * MM
    bounds = np.array([[-BLOCK / 2, -BLOCK / 2, 0.0], [BLOCK / 2, BLOCK / 2, BLOCK_H]])
    bounds += [[-margin] * 3, [margin] * 3]
    return EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.25 * MM)


@pytest.fixture(scope="session")
def cube_points(cube_mesh):
    from mvtop_cli.contact.sdf import sample_surface_points

    return sample_surface_points(cube_mesh, 2000, np.random.default_rng(7))


@pytest.fixture(scope="session")
def cube_fcl(cube_mesh, pocket_mesh):
    from mvtop_cli.contact.fcl_distance import FclDistance

    return FclDistance(cube_mesh, [pocket_mesh])
