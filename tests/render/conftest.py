"""Fixtures for the render tests: sensors, meshes, seeded particle poses, and one numba and
one pyrender renderer per session (tests reach the helpers through the ``scene`` fixture)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render import NumbaMaskRenderer

# A 640x480 RGB camera with an off-centre principal point, as calibrations give.
CAMERA = PinholeCamera(
    width=640, height=480, K=np.array([[615.4, 0.0, 322.1], [0.0, 614.8, 238.7], [0.0, 0.0, 1.0]])
)
# A GelSight-like sensor: 320x240 camera, gel 25 mm in front of it.
TACTILE = PinholeCamera(
    width=320, height=240, K=np.array([[416.0, 0.0, 159.5], [0.0, 416.0, 119.5], [0.0, 0.0, 1.0]])
)
GEL_DISTANCE_M = 0.025


def cube(side_m: float = 0.025) -> trimesh.Trimesh:
    return trimesh.creation.box((side_m, side_m, side_m))


def connector() -> trimesh.Trimesh:
    """An 8 x 5 x 12 mm box, about a small connector's size."""
    return trimesh.creation.box((0.008, 0.005, 0.012))


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return se3.from_quat_xyzw(q, np.zeros((n, 3)))[:, :3, :3]


def camera_particles(rng: np.random.Generator, n: int, distance_m: float, spread_m: float = 0.004) -> np.ndarray:
    """(n, 4, 4) poses around a point ``distance_m`` in front of the camera, random rotations."""
    centre = np.array([0.01, -0.005, distance_m])
    return se3.make_pose(random_rotations(rng, n), centre + rng.normal(scale=spread_m, size=(n, 3)))


def pressed_poses(
    rng: np.random.Generator,
    vertices: np.ndarray,
    n: int,
    depth_range_m: tuple[float, float] = (0.0002, 0.001),
    spread_m: float = 0.002,
    rotations: np.ndarray | None = None,
    max_tilt_rad: float = 0.15,
) -> np.ndarray:
    """(n, 4, 4) poses in the tactile frame with the object's nearest point pressed
    ``depth_range_m`` into the gel plane z = GEL_DISTANCE_M; by default a face is held
    against the gel, tilted by up to ``max_tilt_rad`` and spun about the sensor axis."""
    if rotations is None:
        spin = se3.rotvec_to_matrix(np.column_stack([np.zeros((n, 2)), rng.uniform(-np.pi, np.pi, n)]))
        tilt = se3.rotvec_to_matrix(np.column_stack([rng.uniform(-max_tilt_rad, max_tilt_rad, (n, 2)), np.zeros(n)]))
        rotations = spin @ tilt
    R = rotations
    z_min = np.einsum("nij,vj->nvi", R, vertices)[..., 2].min(axis=1)
    d = rng.uniform(*depth_range_m, size=n)
    xy = rng.normal(scale=spread_m, size=(n, 2))
    t = np.column_stack([xy, GEL_DISTANCE_M - d - z_min])
    return se3.make_pose(R, t)


def sphere(radius_m: float = 0.005) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=radius_m)


def _register(renderer) -> None:
    for name, mesh in (
        ("cube", cube()),
        ("connector", connector()),
        ("sphere", sphere()),
        ("wall", trimesh.creation.box((0.2, 0.2, 0.002))),
    ):
        renderer.add_mesh(name, mesh.vertices, mesh.faces)


@pytest.fixture(scope="session")
def scene() -> SimpleNamespace:
    return SimpleNamespace(
        camera=CAMERA,
        tactile=TACTILE,
        gel_distance_m=GEL_DISTANCE_M,
        cube=cube,
        connector=connector,
        sphere=sphere,
        random_rotations=random_rotations,
        camera_particles=camera_particles,
        pressed_poses=pressed_poses,
    )


@pytest.fixture(scope="session")
def fast() -> NumbaMaskRenderer:
    renderer = NumbaMaskRenderer()
    _register(renderer)
    return renderer


@pytest.fixture(scope="session")
def reference():
    from mvtop_cli.render.pyrender_renderer import PyrenderMaskRenderer

    renderer = PyrenderMaskRenderer()
    _register(renderer)
    yield renderer
    renderer.close()
