"""Environment SDF grid, object surface points and φ against known geometry: a 40 mm
block (20 mm high) with a 25.6 mm square pocket 10 mm deep, and a 10 mm cube."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from mvtop_cli.contact.fcl_distance import FclDistance
from mvtop_cli.contact.sdf import (
    EnvironmentSDF,
    ObjectSignedDistance,
    dist2_point_triangle,
    sample_surface_points,
)
from mvtop_cli.errors import ConfigError, MeshError
from mvtop_cli.geometry import se3

MM = 1e-3
H = 0.25 * MM  # grid resolution of the pocket_sdf fixture


@numba.njit
def _brute_distance(points, V, F):
    out = np.empty(len(points))
    for m in range(len(points)):
        best = np.inf
        for t in range(len(F)):
            a, b, c = F[t, 0], F[t, 1], F[t, 2]
            d = dist2_point_triangle(
                points[m, 0], points[m, 1], points[m, 2],
                V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2], V[c, 0], V[c, 1], V[c, 2],
            )  # fmt: skip
            best = min(best, d)
        out[m] = np.sqrt(best)
    return out


def _exact_sdf(geo, mesh, p):
    """Brute-force distance to every triangle, negative inside the block but not the pocket."""
    d = _brute_distance(p, np.asarray(mesh.vertices), np.asarray(mesh.faces))
    in_block = np.all(np.abs(p[:, :2]) < geo.BLOCK / 2, axis=1) & (p[:, 2] > 0) & (p[:, 2] < geo.BLOCK_H)
    in_pocket = np.all(np.abs(p[:, :2]) < geo.POCKET / 2, axis=1) & (p[:, 2] > geo.FLOOR_Z)
    return np.where(in_block & ~in_pocket, -d, d)


def _rot_y(deg):
    return se3.make_pose(se3.rotvec_to_matrix(np.array([0.0, np.radians(deg), 0.0])), np.zeros(3))


@pytest.fixture(scope="module")
def osd(pocket_sdf, cube_points, cube_fcl):
    return ObjectSignedDistance(pocket_sdf, cube_points, cube_fcl, fcl_above_m=2 * MM)


# --- triangle distance ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "p, expected",
    [
        ((0.2, 0.2, 1.0), 1.0),  # above the face
        ((-1.0, -2.0, 0.0), np.sqrt(5.0)),  # vertex a region
        ((0.5, -1.0, 0.0), 1.0),  # edge ab region
        ((2.0, 2.0, 0.0), np.sqrt(2.0) / 2 * 3),  # edge bc region: distance to x + y = 1
        ((0.0, 3.0, 4.0), np.sqrt(4.0 + 16.0)),  # vertex c region
    ],
)
def test_point_triangle_distance(p, expected):
    a, b, c = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    assert np.sqrt(dist2_point_triangle(*p, *a, *b, *c)) == pytest.approx(expected, rel=1e-12)


def test_point_degenerate_triangle_distance():
    # collinear vertices: distance to the segment from (0,0,0) to (2,0,0)
    d2 = dist2_point_triangle(1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0)
    assert d2 == pytest.approx(1.0)


# --- the grid -------------------------------------------------------------------------------


def test_grid_nodes_match_brute_force(geo, pocket_sdf, pocket_mesh):
    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, n, 4000) for n in pocket_sdf.shape], axis=1)
    nodes = pocket_sdf.origin + pocket_sdf.spacing_m * idx
    exact = _exact_sdf(geo, pocket_mesh, nodes)
    values = pocket_sdf.values[idx[:, 0], idx[:, 1], idx[:, 2]]
    on_surface = np.abs(exact) < 1e-9  # sign undefined there
    assert on_surface.sum() > 10  # the outer walls lie on grid nodes: ties are exercised
    np.testing.assert_allclose(values[~on_surface], exact[~on_surface], atol=2e-6)
    np.testing.assert_allclose(values[on_surface], 0.0, atol=1e-9)


def test_interpolation_within_half_a_cell(geo, pocket_sdf, pocket_mesh):
    rng = np.random.default_rng(1)
    b = pocket_sdf.bounds
    p = rng.uniform(b[0], b[1], size=(4000, 3))
    err = np.abs(pocket_sdf.query(p) - _exact_sdf(geo, pocket_mesh, p))
    assert err.max() < H / 2


def test_interpolation_exact_near_a_single_face(geo, pocket_sdf):
    # over the middle of the pocket floor the field is z - FLOOR_Z: linear, so exact
    rng = np.random.default_rng(2)
    z = rng.uniform(geo.FLOOR_Z - 3 * MM, geo.FLOOR_Z + 3 * MM, 500)
    p = np.c_[rng.uniform(-4 * MM, 4 * MM, (500, 2)), z]
    np.testing.assert_allclose(pocket_sdf.query(p), z - geo.FLOOR_Z, atol=1e-7)


def test_query_outside_box_adds_distance_to_box(geo, pocket_sdf):
    top = pocket_sdf.bounds[1, 2]
    p = np.array([[0.0, 0.0, top + 10 * MM], [0.0, 0.0, top]])
    v = pocket_sdf.query(p)
    assert v[0] == pytest.approx(v[1] + 10 * MM, abs=1e-9)
    # nearest to (0, 0, top) is the pocket's rim, 12.8 mm across and 5 mm down; beyond the
    # box the field only grows with the distance to the box (the true distance is smaller)
    assert v[0] == pytest.approx(np.hypot(geo.POCKET / 2, top - geo.BLOCK_H) + 10 * MM, abs=1e-6)
    assert pocket_sdf.query(np.zeros((2, 5, 3))).shape == (2, 5)


def test_grid_box_covers_bounds(pocket_sdf):
    b = pocket_sdf.bounds
    np.testing.assert_allclose(b[0], [-25 * MM, -25 * MM, -5 * MM])
    assert np.all(b[1] >= 25 * MM - 1e-12)


def test_posed_and_multiple_meshes(geo):
    """The block centred in its own frame, turned and moved in the world, standing on a
    table slab: φ of a cube on the table beside the block and in the pocket."""
    block = geo.pocket_block()
    block.apply_translation([0, 0, -geo.BLOCK_H / 2])
    R_quarter_turn = se3.rotvec_to_matrix(np.array([0, 0, np.pi / 2]))
    T_world_block = se3.make_pose(R_quarter_turn, [0.01, 0.0, geo.BLOCK_H / 2])
    table = trimesh.creation.box(extents=[0.2, 0.2, 0.01])
    T_world_env = np.stack([T_world_block, geo.translation(z=-0.005)])  # table top at z = 0
    bounds = np.array([[-0.02, -0.03, -0.003], [0.05, 0.03, 0.025]])
    sdf = EnvironmentSDF.from_meshes([block, table], T_world_env, bounds, 0.5 * MM)
    cube = geo.cube_object()
    pts = sample_surface_points(cube, 500, np.random.default_rng(0))
    fcl = FclDistance(cube, [block, table], T_world_env)
    x_side = 0.01 - geo.BLOCK / 2 - 3 * MM - geo.CUBE / 2  # 3 mm left of the block
    for z, expected in [(1 * MM, 1 * MM), (0.0, 0.0), (-0.3 * MM, -0.3 * MM), (5 * MM, 3 * MM)]:
        T = geo.translation(x_side, 0.0, z)
        assert sdf.phi(T, pts) == pytest.approx(expected, abs=1e-6)
        assert fcl.distance(T) == pytest.approx(max(expected, 0.0), abs=1e-9)
    T = geo.translation(0.01, 0.0, geo.FLOOR_Z + 2 * MM)  # in the pocket, 2 mm up
    assert sdf.phi(T, pts) == pytest.approx(2 * MM, abs=1e-6)


def test_cache_round_trip(geo, tmp_path, pocket_mesh):
    bounds = np.array([[-0.01, -0.01, 0.005], [0.01, 0.01, 0.015]])
    a = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("env_sdf_*.npz"))) == 1
    b = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM, cache_dir=tmp_path)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.origin, b.origin)
    assert a.spacing_m == b.spacing_m
    # another pose is another key
    moved = geo.translation(z=1 * MM)[None]
    c = EnvironmentSDF.from_meshes([pocket_mesh], moved, bounds, 0.5 * MM, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("env_sdf_*.npz"))) == 2
    assert c.query(np.array([0.0, 0.0, 0.012])) == pytest.approx(0.012 - geo.FLOOR_Z - 1 * MM, abs=1e-7)


def test_a_corrupt_cache_entry_is_rebuilt_and_an_unwritable_cache_only_costs_the_build(tmp_path, pocket_mesh):
    bounds = np.array([[-0.01, -0.01, 0.005], [0.01, 0.01, 0.015]])
    a = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM, cache_dir=tmp_path)
    (entry,) = tmp_path.glob("env_sdf_*.npz")
    entry.write_bytes(entry.read_bytes()[:100])  # truncated, e.g. by a full disk
    b = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM, cache_dir=tmp_path)
    np.testing.assert_array_equal(a.values, b.values)
    with np.load(entry) as data:  # and the entry was written again, whole
        np.testing.assert_array_equal(data["values"], a.values)
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    c = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM, cache_dir=blocked / "cache")
    np.testing.assert_array_equal(a.values, c.values)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([entry.name, "file"])  # no temporary left


def test_open_mesh_rejected():
    box = trimesh.creation.box(extents=[0.01] * 3)
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1])
    with pytest.raises(MeshError, match="not watertight"):
        EnvironmentSDF.from_meshes([open_box], None, np.array([[-0.01] * 3, [0.01] * 3]), 1e-3)


def test_split_seam_vertices_are_merged():
    """OBJ exports duplicate vertices along seams; positions alone make the mesh closed."""
    box = trimesh.creation.box(extents=[0.01] * 3)
    v = box.vertices[box.faces].reshape(-1, 3)  # every face with its own vertices
    soup = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
    assert not soup.is_watertight
    sdf = EnvironmentSDF.from_meshes([soup], None, np.array([[-0.01] * 3, [0.01] * 3]), 0.5e-3)
    assert sdf.query(np.zeros(3)) == pytest.approx(-0.005, abs=1e-7)


def test_bad_bounds_rejected(pocket_mesh):
    with pytest.raises(ValueError, match="bounds_world"):
        EnvironmentSDF.from_meshes([pocket_mesh], None, np.array([[0, 0, 0], [0.01, -0.01, 0.01]]), 1e-3)


# --- surface points -------------------------------------------------------------------------


def test_surface_points_deterministic_and_on_surface(geo, cube_mesh):
    a = sample_surface_points(cube_mesh, 300, np.random.default_rng(3))
    b = sample_surface_points(cube_mesh, 300, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (300, 3)
    c = a - [0, 0, geo.CUBE / 2]  # cube-centred
    np.testing.assert_allclose(np.abs(c).max(axis=1), geo.CUBE / 2, atol=1e-12)


def test_surface_points_include_corners_and_edges(geo, cube_mesh):
    pts = sample_surface_points(cube_mesh, 300, np.random.default_rng(4))
    corners = np.unique(np.asarray(cube_mesh.vertices), axis=0)
    d = np.linalg.norm(pts[:, None] - corners[None], axis=2).min(axis=0)
    np.testing.assert_allclose(d, 0.0, atol=1e-15)
    c = pts - [0, 0, geo.CUBE / 2]
    on_edge = np.sum(np.isclose(np.abs(c), geo.CUBE / 2, atol=1e-12), axis=1) >= 2
    assert on_edge.sum() >= 300 // 4  # corners and edge points: about half


def test_surface_points_spread_evenly(cube_mesh):
    pts = sample_surface_points(cube_mesh, 600, np.random.default_rng(5))
    probe, _ = trimesh.sample.sample_surface(cube_mesh, 20000, seed=0)
    gap = cKDTree(pts).query(probe)[0]
    # 600 points on 600 mm^2: an even spread leaves gaps under ~1 mm, random ones ~2-3 mm
    assert gap.max() < 1.2 * MM


def test_surface_points_reject_empty_mesh():
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(MeshError, match="empty"):
        sample_surface_points(empty, 10, np.random.default_rng(0))


# --- φ --------------------------------------------------------------------------------------


@pytest.mark.parametrize("gap_mm", [0.3, 1.0, 3.0])
def test_separated_in_pocket(geo, osd, cube_fcl, gap_mm):
    gap = gap_mm * MM
    T = geo.translation(1 * MM, -2 * MM, geo.FLOOR_Z + gap)
    assert osd.phi_grid(T) == pytest.approx(gap, abs=1e-6)  # flat floor: exact, not just < H
    assert cube_fcl.distance(T) == pytest.approx(gap, abs=1e-12)
    assert osd.phi(T) == pytest.approx(gap, abs=1e-6)


def test_separated_over_rim_and_near_wall(geo, osd, cube_fcl):
    T = geo.translation(16 * MM, 0.0, geo.BLOCK_H + 1.5 * MM)  # over the rim, 1.5 mm up
    assert osd.phi_grid(T) == pytest.approx(1.5 * MM, abs=H)
    assert cube_fcl.distance(T) == pytest.approx(1.5 * MM, abs=1e-12)
    # 0.4 mm from the +x pocket wall, 2 mm above the floor
    T = geo.translation(geo.POCKET / 2 - geo.CUBE / 2 - 0.4 * MM, 0.0, geo.FLOOR_Z + 2 * MM)
    assert osd.phi_grid(T) == pytest.approx(0.4 * MM, abs=H)
    assert cube_fcl.distance(T) == pytest.approx(0.4 * MM, abs=1e-12)


def test_tilted_cube_edge_gap(geo, osd, cube_fcl):
    # turned 30 deg about y around the bottom-face centre, its lowest edge dips 2.5 mm
    T = geo.translation(0.0, 0.0, geo.FLOOR_Z + 3.5 * MM) @ _rot_y(30)
    assert osd.phi_grid(T) == pytest.approx(1 * MM, abs=1e-6)
    assert cube_fcl.distance(T) == pytest.approx(1 * MM, abs=1e-12)
    T = geo.translation(0.0, 0.0, geo.FLOOR_Z + 2.0 * MM) @ _rot_y(30)  # 0.5 mm into the floor
    assert osd.phi(T) == pytest.approx(-0.5 * MM, abs=0.1 * MM)


def test_touching_is_zero(geo, osd, cube_fcl):
    T = geo.translation(0.0, 0.0, geo.FLOOR_Z)
    assert osd.phi(T) == pytest.approx(0.0, abs=1e-6)
    assert cube_fcl.distance(T) == pytest.approx(0.0, abs=1e-12)
    T = geo.translation(geo.POCKET / 2 - geo.CUBE / 2, 0.0, geo.FLOOR_Z + 2 * MM)  # flush with a wall
    assert osd.phi(T) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("depth_mm", [0.1, 0.5, 2.0])
def test_pushed_into_floor(geo, osd, cube_fcl, depth_mm):
    T = geo.translation(0.0, 1 * MM, geo.FLOOR_Z - depth_mm * MM)
    assert osd.phi(T) == pytest.approx(-depth_mm * MM, abs=0.1 * MM)
    assert cube_fcl.distance(T) == 0.0  # FCL: colliding meshes give 0, not the depth


def test_pushed_into_wall(geo, osd):
    T = geo.translation(geo.POCKET / 2 - geo.CUBE / 2 + 0.5 * MM, 0.0, geo.FLOOR_Z + 2 * MM)
    assert osd.phi(T) == pytest.approx(-0.5 * MM, abs=0.1 * MM)


def test_phi_decreases_as_cube_descends(geo, osd):
    z = geo.FLOOR_Z + np.linspace(3 * MM, -2 * MM, 51)
    T = np.stack([geo.translation(0.0, 0.0, zi) for zi in z])
    phi = osd.phi(T)
    assert np.all(np.diff(phi) < 0)
    np.testing.assert_allclose(phi, z - geo.FLOOR_Z, atol=1e-6)


def test_far_pose_uses_fcl(geo, osd, pocket_sdf, cube_points):
    # 30 mm above the top face: outside the grid box and beyond fcl_above_m
    T = geo.translation(16 * MM, 0.0, geo.BLOCK_H + 30 * MM)
    assert osd.phi(T) == pytest.approx(30 * MM, abs=1e-12)
    # without FCL the grid's extension outside its box is used
    grid_only = ObjectSignedDistance(pocket_sdf, cube_points, None)
    assert grid_only.phi(T) == pytest.approx(30 * MM, abs=H)


def test_minimum_outside_box_uses_fcl(geo, pocket_mesh, cube_points, cube_fcl):
    """A grid box that stops at the rim: over the rim, 1 mm above the block's top face, the
    grid only sees the box, FCL the real gap, even below ``fcl_above_m``."""
    bounds = np.array([[-13 * MM, -13 * MM, 5 * MM], [13 * MM, 13 * MM, 15 * MM]])
    sdf = EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.5 * MM)
    T = geo.translation(16 * MM, 0.0, geo.BLOCK_H + 1 * MM)
    with_fcl = ObjectSignedDistance(sdf, cube_points, cube_fcl, fcl_above_m=50 * MM)
    assert with_fcl.phi(T) == pytest.approx(1 * MM, abs=1e-12)
    assert with_fcl.phi_grid(T) > 2 * MM  # what the grid alone says there


def test_batched_equals_looped_and_brute_force(geo, osd, pocket_sdf, cube_points):
    rng = np.random.default_rng(11)
    n = 64
    lo = [-15 * MM, -15 * MM, geo.FLOOR_Z - 2 * MM]
    hi = [15 * MM, 15 * MM, geo.BLOCK_H + 8 * MM]
    T = se3.make_pose(se3.rotvec_to_matrix(rng.normal(0.0, 0.5, (n, 3))), rng.uniform(lo, hi, (n, 3)))
    batched = osd.phi(T)
    looped = np.array([osd.phi(T_i) for T_i in T])
    np.testing.assert_array_equal(batched, looped)
    # the leaf culling never changes the minimum
    np.testing.assert_array_equal(osd.phi_grid(T), pocket_sdf.phi(T, cube_points))
    assert (batched < 0).any() and (batched > 2 * MM).any()  # both regimes exercised


def test_from_meshes_builds_everything(geo, pocket_mesh):
    bounds = np.array([[-0.016, -0.016, 0.005], [0.016, 0.016, 0.025]])
    sd = ObjectSignedDistance.from_meshes(
        geo.cube_object(), [pocket_mesh], None, bounds,
        rng=np.random.default_rng(0), resolution_m=0.5 * MM, n_points=500,
    )  # fmt: skip
    assert sd.points_object.shape == (500, 3)
    assert isinstance(sd.fcl_distance, FclDistance)
    assert sd.phi(geo.translation(z=geo.FLOOR_Z + 1 * MM)) == pytest.approx(1 * MM, abs=1e-6)


def test_mesh_outside_box_still_seen(geo):
    """A block 8 mm beside the grid box (farther than the exact band) is found by the
    lattice seeding and the sweeps: distances inside the box are exact."""
    block = trimesh.creation.box(extents=[10 * MM] * 3)
    T = geo.translation(x=-(5 + 8 + 10) * MM)  # its +x face 8 mm left of the box at x = -10 mm
    bounds = np.array([[-10 * MM] * 3, [10 * MM] * 3])
    sdf = EnvironmentSDF.from_meshes([block], T[None], bounds, 0.5 * MM)
    rng = np.random.default_rng(0)
    v, f = np.asarray(block.vertices) + T[:3, 3], np.asarray(block.faces)
    idx = np.stack([rng.integers(0, n, 500) for n in sdf.shape], axis=1)
    nodes = sdf.origin + sdf.spacing_m * idx
    np.testing.assert_allclose(sdf.values[tuple(idx.T)], _brute_distance(nodes, v, f), atol=1e-6)
    # between nodes the field curves (distance to the block's edges): ~h^2 / 8d off
    p = rng.uniform(-10 * MM, 10 * MM, (500, 3))
    np.testing.assert_allclose(sdf.query(p), _brute_distance(p, v, f), atol=2e-5)


def test_grid_too_large_rejected(pocket_mesh):
    bounds = np.array([[-0.5] * 3, [0.5] * 3])
    with pytest.raises(ConfigError, match="exceeds"):
        EnvironmentSDF.from_meshes([pocket_mesh], None, bounds, 0.25 * MM)


def test_surface_points_on_smooth_mesh():
    """No sharp edges (a sphere): all points come from the faces, spread evenly."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10 * MM)
    pts = sample_surface_points(sphere, 400, np.random.default_rng(0))
    assert pts.shape == (400, 3)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 10 * MM, atol=0.05 * MM)
