"""φ on real CAD: the IndustReal 12 mm rectangular peg in its socket (metres, shared frame:
the socket's hole floor is at z = 3 mm, and the peg at identity rests on it)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from _real_data import REAL_DATA, needs_real_data

from mvtop_cli.contact.fcl_distance import FclDistance
from mvtop_cli.contact.sdf import EnvironmentSDF, ObjectSignedDistance, sample_surface_points

MM = 1e-3
INDUSTREAL = REAL_DATA / "industreal_meshes"
SOCKET = INDUSTREAL / "industreal_tray_insert_rectangular_peg_12mm.obj"
PEG = INDUSTREAL / "industreal_rectangular_peg_12mm.obj"


def translation(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T

pytestmark = needs_real_data


@pytest.fixture(scope="module")
def socket():
    return trimesh.load(SOCKET, force="mesh")


@pytest.fixture(scope="module")
def peg():
    return trimesh.load(PEG, force="mesh")


@pytest.fixture(scope="module")
def geometry(socket, peg):
    """Hole size from the socket's wall vertices, the peg's cross-section from its bounds."""
    v = np.asarray(socket.vertices)
    wall = (np.abs(v[:, 0]) < 8 * MM) & (np.abs(v[:, 1]) < 8 * MM) & (v[:, 2] > 5 * MM) & (v[:, 2] < 25 * MM)
    hole = np.ptp(v[wall][:, :2], axis=0)
    floor_z = v[(np.abs(v[:, 0]) < 5 * MM) & (np.abs(v[:, 1]) < 3 * MM)][:, 2].max()
    peg_xy = np.ptp(np.asarray(peg.vertices)[:, :2], axis=0)
    return {
        "clearance": (hole - peg_xy) / 2,  # per side, x and y
        "peg_xy": peg_xy,
        "floor_z": floor_z,
        "peg_bottom_z": np.asarray(peg.vertices)[:, 2].min(),
        "top_z": v[:, 2].max(),
    }


@pytest.fixture(scope="module")
def contact(socket, peg):
    bounds = socket.bounds + [[-2 * MM] * 3, [2 * MM] * 3]
    sdf = EnvironmentSDF.from_meshes([socket], None, bounds, 0.25 * MM)
    points = sample_surface_points(peg, 2000, np.random.default_rng(0))
    return ObjectSignedDistance(sdf, points, FclDistance(peg, [socket]), fcl_above_m=2 * MM)


def test_mesh_frames(geometry):
    assert geometry["floor_z"] == pytest.approx(3 * MM)
    assert geometry["peg_bottom_z"] == pytest.approx(geometry["floor_z"])
    assert geometry["top_z"] == pytest.approx(28 * MM)
    # 13 x 9 mm hole for an 11.96 x 7.91 mm peg: ~0.52-0.55 mm per side
    np.testing.assert_allclose(geometry["clearance"], [0.5215 * MM, 0.545 * MM], atol=5e-3 * MM)


def test_centred_peg_phi_is_the_clearance(contact, geometry):
    T = translation(z=1 * MM)  # centred, 1 mm above the hole floor
    expected = geometry["clearance"].min()
    assert contact.phi_grid(T) == pytest.approx(expected, abs=0.02 * MM)
    assert contact.fcl_distance.distance(T) == pytest.approx(expected, abs=1e-9)
    assert contact.phi(T) == pytest.approx(expected, abs=0.02 * MM)


@pytest.mark.parametrize("axis", [0, 1])
def test_shifted_into_wall(contact, geometry, axis):
    shift = np.array([0.0, 0.0, 1 * MM])  # 1 mm above the floor
    shift[axis] = 1 * MM
    T = translation(*shift)
    expected = -(1 * MM - geometry["clearance"][axis])
    assert contact.phi(T) == pytest.approx(expected, abs=0.1 * MM)
    assert contact.fcl_distance.distance(T) == 0.0


def test_partly_shifted_still_separated(contact, geometry):
    T = translation(x=0.3 * MM, z=1 * MM)
    expected = min(geometry["clearance"][0] - 0.3 * MM, geometry["clearance"][1])
    assert contact.phi(T) == pytest.approx(expected, abs=0.02 * MM)
    assert contact.fcl_distance.distance(T) == pytest.approx(expected, abs=1e-9)


def test_resting_on_floor_and_pushed_into_it(contact):
    assert contact.phi(np.eye(4)) == pytest.approx(0.0, abs=0.02 * MM)
    assert contact.phi(translation(z=-0.5 * MM)) == pytest.approx(-0.5 * MM, abs=0.1 * MM)


def test_above_top_face(contact, geometry):
    # beside the hole, bottom face 1.5 mm above the socket's flat top face
    T = translation(x=10 * MM, z=geometry["top_z"] - geometry["peg_bottom_z"] + 1.5 * MM)
    assert contact.phi_grid(T) == pytest.approx(1.5 * MM, abs=0.25 * MM)
    assert contact.fcl_distance.distance(T) == pytest.approx(1.5 * MM, abs=1e-9)
    # far above (partly outside the grid box): FCL's exact distance
    T = translation(x=10 * MM, z=geometry["top_z"] - geometry["peg_bottom_z"] + 20 * MM)
    assert contact.phi(T) == pytest.approx(20 * MM, abs=1e-9)


@pytest.mark.parametrize("deg", [1.0, 4.0, 6.0])
def test_tilted_peg_in_hole(contact, geometry, deg):
    """The peg 1 mm above the floor, tilted about y around its point 12 mm above its bottom
    face: its bottom corner and its side at the hole's mouth (12 mm above the pivot) swing
    out by (w/2) cos θ + 12 mm sin θ, against a hole half-width of w/2 + clearance. Past
    ~2.4 deg it jams into the walls."""
    th = np.radians(deg)
    pivot = [0.0, 0.0, geometry["peg_bottom_z"] + 12 * MM]
    R = trimesh.transformations.rotation_matrix(th, [0, 1, 0], point=pivot)
    T = translation(z=1 * MM) @ R
    half_w = geometry["peg_xy"][0] / 2
    expected = half_w + geometry["clearance"][0] - (half_w * np.cos(th) + 12 * MM * np.sin(th))
    assert contact.phi(T) == pytest.approx(expected, abs=0.02 * MM)
    if expected > 0:
        assert contact.fcl_distance.distance(T) == pytest.approx(expected, abs=1e-9)
