"""Tests for mvtop_cli.sim.objects: mesh validity, dimensions, clearances and symmetries."""

from __future__ import annotations

import itertools
from pathlib import Path

import fcl
import numpy as np
import pytest
import trimesh
from _real_data import REAL_DATA, needs_real_data

from mvtop_cli.errors import MvtopError
from mvtop_cli.sim.objects import ObjectSpec, boxes_to_mesh, get_object, list_objects

NAMES = ["cube", "shaft_peg", "plug", "conn1", "conn2"]
INDUSTREAL = REAL_DATA / "industreal_meshes"
MM = 1e-3


# ----------------------------------------------------------------------------- helpers


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


def distance(a: trimesh.Trimesh, T_a: np.ndarray, b: trimesh.Trimesh, T_b: np.ndarray) -> float:
    request, result = fcl.DistanceRequest(), fcl.DistanceResult()
    return float(fcl.distance(_fcl_object(a, T_a), _fcl_object(b, T_b), request, result))


def translation(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def point_mesh_distance(points: np.ndarray, mesh: trimesh.Trimesh, chunk: int = 64) -> np.ndarray:
    """Exact distance (n,) [m] from points (n, 3) [m] to the surface of ``mesh`` (brute force).

    Works in millimetres: trimesh's closest-point region tests compare products of dot
    products (length^4) with a fixed 1e-13 tolerance, which misplaces points on
    millimetre-sized triangles expressed in metres.
    """
    tris = mesh.triangles * 1e3
    points = np.asarray(points) * 1e3
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        p = points[i : i + chunk]
        pairs_p = np.repeat(p, len(tris), axis=0)
        pairs_t = np.tile(tris, (len(p), 1, 1))
        closest = trimesh.triangles.closest_point(pairs_t, pairs_p)
        d = np.linalg.norm(closest - pairs_p, axis=1).reshape(len(p), len(tris))
        out[i : i + chunk] = d.min(axis=1)
    return out * 1e-3


def section_loops(mesh: trimesh.Trimesh, z: float) -> list[np.ndarray]:
    """Closed loops (each (n, 2) x/y) where the plane at height ``z`` [m] cuts ``mesh``."""
    path = mesh.section(plane_origin=[0.0, 0.0, z], plane_normal=[0.0, 0.0, 1.0])
    assert path is not None, f"plane z={z} misses the mesh"
    return [np.asarray(loop)[:, :2] for loop in path.discrete]


def loop_boxes(loops: list[np.ndarray], max_extent: float) -> np.ndarray:
    """(k, 2, 2) [[xmin, ymin], [xmax, ymax]] of the loops smaller than ``max_extent`` [m],
    sorted by centre x then y."""
    boxes = [np.stack([l.min(0), l.max(0)]) for l in loops if np.ptp(l, axis=0).max() < max_extent]
    centres = np.array([b.mean(0) for b in boxes])
    order = np.lexsort((np.round(centres[:, 1], 7), np.round(centres[:, 0], 7)))
    return np.array(boxes)[order]


def axis_rotations() -> np.ndarray:
    """All 24 proper rotations that permute the coordinate axes (24, 3, 3)."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0:
                mats.append(R)
    return np.stack(mats)


# ----------------------------------------------------------------------------- registry


def test_list_objects_in_paper_order():
    assert list_objects() == NAMES


def test_unknown_object_names_valid_ones_and_suggests():
    with pytest.raises(MvtopError) as info:
        get_object("plgu")
    message = str(info.value)
    assert "did you mean 'plug'" in message
    for name in NAMES:
        assert name in message


def test_specs_are_cached_and_frozen():
    spec = get_object("cube")
    assert get_object("cube") is spec
    assert isinstance(spec, ObjectSpec)
    with pytest.raises(AttributeError):
        spec.clearance_m = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        spec.grasp[0, 3] = 1.0


# ----------------------------------------------------------------------------- mesh validity


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("part", ["mesh", "receptacle_mesh"])
def test_meshes_are_clean_closed_solids(name, part):
    mesh = getattr(get_object(name), part)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.is_volume and mesh.volume > 0
    assert mesh.euler_number == 2  # one closed genus-0 surface: no pinched edges or corners
    assert len(mesh.split(only_watertight=False)) == 1
    assert len(mesh.faces) < 5000
    assert mesh.area_faces.min() > 1e-10  # [m^2] no degenerate faces


@pytest.mark.parametrize("name", NAMES)
def test_frames_follow_conventions(name):
    spec = get_object(name)
    # object: leading face at z = 0, body along +z; receptacle: mouth at z = 0, body below
    assert spec.mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-12)
    assert spec.receptacle_mesh.bounds[1, 2] == pytest.approx(0.0, abs=1e-12)
    # the leading face and the mouth are centred on the z axis
    lead = np.concatenate(section_loops(spec.mesh, 0.1 * MM))
    mouth = section_loops(spec.receptacle_mesh, -0.1 * MM)
    outer = max(mouth, key=lambda l: np.ptp(l, axis=0).prod())
    assert np.abs(lead.min(0) + lead.max(0)).max() < 3.0 * MM  # keys may make it off-centre
    assert np.allclose(outer.min(0) + outer.max(0), 0.0, atol=1e-9)
    T = spec.T_receptacle_object_inserted
    assert np.allclose(T, translation(z=-spec.insertion_depth_m))


def test_box_mesher_rejects_nothing_it_should_keep():
    # an L-shaped solid made of two overlapping boxes has the union's volume
    mesh = boxes_to_mesh([(True, ((0, 2), (0, 1), (0, 1))), (True, ((0, 1), (0, 2), (0, 1)))], scale=1.0)
    assert mesh.is_volume
    assert mesh.volume == pytest.approx(3.0)
    # cutting a blind hole keeps it watertight and removes the hole's volume
    mesh = boxes_to_mesh([(True, ((0, 3), (0, 3), (0, 3))), (False, ((1, 2), (1, 2), (1, 3)))], scale=1.0)
    assert mesh.is_volume
    assert mesh.volume == pytest.approx(25.0)


# ----------------------------------------------------------------------------- dimensions


def test_cube_and_pocket_dimensions():
    spec = get_object("cube")
    assert np.allclose(spec.mesh.extents, 25.0 * MM)
    pocket = loop_boxes(section_loops(spec.receptacle_mesh, -1.0 * MM), 30 * MM)
    assert len(pocket) == 1
    side = np.ptp(pocket[0], axis=0)
    assert np.allclose(side, 25.6 * MM, atol=1e-9)
    assert spec.clearance_m == pytest.approx((side[0] - spec.mesh.extents[0]) / 2)


@needs_real_data
def test_shaft_peg_matches_industreal_12mm_peg():
    spec = get_object("shaft_peg")
    real_peg = trimesh.load(INDUSTREAL / "industreal_rectangular_peg_12mm.obj", force="mesh")
    real_tray = trimesh.load(INDUSTREAL / "industreal_tray_insert_rectangular_peg_12mm.obj", force="mesh")
    assert np.allclose(spec.mesh.extents[:2], real_peg.extents[:2], atol=0.02 * MM)
    assert 40 * MM <= spec.mesh.extents[2] <= real_peg.extents[2] + 1e-9
    assert np.allclose(spec.receptacle_mesh.extents, real_tray.extents, atol=0.01 * MM)
    hole = loop_boxes(section_loops(spec.receptacle_mesh, -10 * MM), 20 * MM)
    assert len(hole) == 1
    diametral = np.ptp(hole[0], axis=0) - spec.mesh.extents[:2]
    assert np.all((diametral > 0.5 * MM) & (diametral < 0.65 * MM))
    assert np.allclose(diametral / 2, spec.clearance_m)
    # 25 mm deep hole, like the IndustReal tray (its peg file sits 3 mm above the tray bottom)
    hole_floor = -spec.insertion_depth_m - 0.5 * MM
    assert section_loops(spec.receptacle_mesh, hole_floor + 0.01 * MM)
    assert len(section_loops(spec.receptacle_mesh, hole_floor - 0.01 * MM)) == 1
    assert hole_floor == pytest.approx(-(real_tray.extents[2] - real_peg.bounds[0, 2]))


def test_plug_blades_and_socket_follow_nema_1_15():
    spec = get_object("plug")
    blades = loop_boxes(section_loops(spec.mesh, 5 * MM), 10 * MM)
    assert len(blades) == 2
    sizes = np.ptp(blades, axis=1)
    assert np.allclose(sizes, [1.52 * MM, 6.35 * MM], atol=1e-9)
    centres = blades.mean(axis=1)
    assert np.linalg.norm(centres[1] - centres[0]) == pytest.approx(12.7 * MM, abs=1e-9)
    # blade length: the lowest point wider than a blade is the body's insertion face
    body_start = spec.mesh.vertices[np.abs(spec.mesh.vertices[:, 1]) > 4 * MM, 2].min()
    assert body_start == pytest.approx(15.9 * MM)
    body = np.ptp(spec.mesh.vertices[spec.mesh.vertices[:, 2] >= body_start - 1e-12], axis=0)
    assert np.allclose(body, [30 * MM, 22 * MM, 20 * MM])
    slots = loop_boxes(section_loops(spec.receptacle_mesh, -5 * MM), 10 * MM)
    assert len(slots) == 2
    assert np.allclose(slots.mean(axis=1), centres, atol=1e-9)  # aligned when inserted
    per_side = (np.ptp(slots, axis=1) - sizes) / 2
    assert np.allclose(per_side, spec.clearance_m)
    assert 0.1 * MM < spec.clearance_m < 0.5 * MM


@pytest.mark.parametrize(
    "name, pitch, rows, cols",
    [("conn1", 3.81 * MM, 1, 6), ("conn2", 4.14 * MM, 2, 3)],
)
def test_connector_pitch_measured_on_pins_and_cavities(name, pitch, rows, cols):
    spec = get_object(name)
    cavities = loop_boxes(section_loops(spec.mesh, 2.5 * MM), 3 * MM)
    pins = loop_boxes(section_loops(spec.receptacle_mesh, -2.0 * MM), 2 * MM)
    assert len(cavities) == len(pins) == 6
    for boxes in (cavities, pins):
        centres = boxes.mean(axis=1)
        xs = np.unique(np.round(centres[:, 0], 7))
        ys = np.unique(np.round(centres[:, 1], 7))
        assert len(xs) * len(ys) == 6
        assert {len(xs), len(ys)} == {rows, cols}
        for coords in (xs, ys):
            if len(coords) > 1:
                assert np.allclose(np.diff(coords), pitch, atol=1e-9)
    # pins stand centred under the cavities of the inserted housing, inside the clearance
    assert np.allclose(pins.mean(axis=1), cavities.mean(axis=1), atol=1e-9)
    per_side = (np.ptp(cavities, axis=1) - np.ptp(pins, axis=1)) / 2
    assert np.all(per_side >= spec.clearance_m)


def test_connector_housing_sizes():
    conn1, conn2 = get_object("conn1"), get_object("conn2")
    body1 = np.ptp(section_loops(conn1.mesh, 13.9 * MM)[0], axis=0)  # above the cavities
    assert np.allclose(body1, [24.0 * MM, 8.0 * MM])  # 23 mm body + 1 mm key rib
    assert conn1.mesh.extents[2] == pytest.approx(14 * MM)
    body2 = np.ptp(section_loops(conn2.mesh, 12.9 * MM)[0], axis=0)  # above the latch
    assert np.allclose(body2, [9.6 * MM, 13.0 * MM])
    assert conn2.mesh.extents[2] == pytest.approx(13 * MM)


# ----------------------------------------------------------------------------- clearance


@pytest.mark.parametrize("name", NAMES)
def test_inserted_object_clears_receptacle_by_its_clearance(name):
    spec = get_object(name)
    T_in = spec.T_receptacle_object_inserted
    assert spec.clearance_m > 0
    assert not collides(spec.mesh, T_in, spec.receptacle_mesh, np.eye(4))
    # the smallest gap at the nominal pose is the stated clearance
    gap = distance(spec.mesh, T_in, spec.receptacle_mesh, np.eye(4))
    assert gap == pytest.approx(spec.clearance_m, abs=1e-7)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("direction", [(1, 0), (-1, 0), (0, 1), (0, -1)])
def test_lateral_shift_within_tolerance_fits_beyond_collides(name, direction):
    spec = get_object(name)
    T_in = spec.T_receptacle_object_inserted
    dx, dy = direction
    c = spec.clearance_m
    inside = translation(0.5 * c * dx, 0.5 * c * dy) @ T_in
    outside = translation((2 * c + 0.1 * MM) * dx, (2 * c + 0.1 * MM) * dy) @ T_in
    assert not collides(spec.mesh, inside, spec.receptacle_mesh, np.eye(4))
    assert collides(spec.mesh, outside, spec.receptacle_mesh, np.eye(4))


@pytest.mark.parametrize("name", NAMES)
def test_inserted_object_bottoms_out_just_below_its_insertion_depth(name):
    spec = get_object(name)
    d = spec.insertion_depth_m
    assert not collides(spec.mesh, translation(z=-d - 0.4 * MM), spec.receptacle_mesh, np.eye(4))
    assert collides(spec.mesh, translation(z=-d - 0.6 * MM), spec.receptacle_mesh, np.eye(4))


@pytest.mark.parametrize("name", NAMES)
def test_object_must_be_aligned_to_enter(name):
    # a 5 degree yaw or tilt about the inserted object's leading face jams every part
    spec = get_object(name)
    for axis in ([0, 0, 1], [1, 0, 0], [0, 1, 0]):
        turn = trimesh.transformations.rotation_matrix(np.radians(5.0), axis)
        T = spec.T_receptacle_object_inserted @ turn
        assert collides(spec.mesh, T, spec.receptacle_mesh, np.eye(4)), axis


# ----------------------------------------------------------------------------- symmetry


def _is_symmetry(mesh: trimesh.Trimesh, T: np.ndarray, points: np.ndarray) -> float:
    """Largest distance [m] from the transformed sample ``points`` to ``mesh``'s surface."""
    moved = trimesh.transform_points(points, T)
    return float(point_mesh_distance(moved, mesh).max())


@pytest.mark.parametrize("name", NAMES)
def test_symmetry_group_is_exactly_the_mesh_symmetries(name):
    spec = get_object(name)
    mesh, S = spec.mesh, spec.symmetry
    assert S.ndim == 3 and S.shape[1:] == (4, 4)
    assert np.allclose(S[0], np.eye(4))
    R = S[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    # closed under composition
    for a, b in itertools.product(S, S):
        assert np.min(np.abs(S - a @ b).reshape(len(S), -1).max(axis=1)) < 1e-12
    points, _ = trimesh.sample.sample_surface(mesh, 150, seed=7)
    for T in S:
        assert _is_symmetry(mesh, T, points) < 1e-9
    # completeness: a proper symmetry of an axis-aligned box solid permutes the axes and
    # fixes the centre of mass, so trying all 24 such rotations finds every one
    centre = mesh.center_mass
    found = 0
    for Rc in axis_rotations():
        T = np.eye(4)
        T[:3, :3] = Rc
        T[:3, 3] = centre - Rc @ centre
        listed = np.min(np.abs(S - T).reshape(len(S), -1).max(axis=1)) < 1e-9
        error = _is_symmetry(mesh, T, points[:60])
        assert (error < 1e-9) == listed, (Rc, error)
        found += listed
    assert found == len(S)
    expected = {"cube": 24, "shaft_peg": 4, "plug": 2, "conn1": 1, "conn2": 1}[name]
    assert len(S) == expected


# ----------------------------------------------------------------------------- appearance


def test_appearance_hints():
    cube, peg, plug = get_object("cube"), get_object("shaft_peg"), get_object("plug")
    assert cube.material == "wood" and peg.material == "metal" and plug.material == "plastic"
    r, g, b, _ = cube.color_rgba
    assert r > g > b  # brown
    assert max(peg.color_rgba[:3]) - min(peg.color_rgba[:3]) < 0.05  # grey
    assert min(plug.color_rgba[:3]) > 0.8  # white/ivory
    for name in NAMES:
        spec = get_object(name)
        for rgba in (spec.color_rgba, spec.receptacle_color_rgba):
            assert len(rgba) == 4 and all(0.0 <= v <= 1.0 for v in rgba)
        assert 0.0 <= spec.metallic <= 1.0 and 0.0 <= spec.roughness <= 1.0


# ----------------------------------------------------------------------------- exported files

REPO = Path(__file__).parents[2]


def _export_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("export_meshes", REPO / "scripts" / "export_meshes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _expected_meshes() -> dict[str, trimesh.Trimesh]:
    from mvtop_cli.sim.gripper import gripper_meshes
    from mvtop_cli.sim.scene import board_mesh

    meshes = {"finger": gripper_meshes()["left"], "board": board_mesh()}
    for name in NAMES:
        meshes[name] = get_object(name).mesh
        meshes[f"{name}_receptacle"] = get_object(name).receptacle_mesh
    return meshes


def test_export_is_deterministic_and_matches_the_kept_files(tmp_path):
    script = _export_script()
    first = script.export_all(tmp_path / "a")
    second = script.export_all(tmp_path / "b")
    assert sorted(p.name for p in first) == sorted(f"{n}.obj" for n in _expected_meshes())
    for a, b in zip(first, second):
        assert a.read_bytes() == b.read_bytes()
        kept = REPO / "configs" / "meshes" / a.name
        assert kept.read_bytes() == a.read_bytes(), f"{kept} is stale: rerun scripts/export_meshes.py"


@pytest.mark.parametrize("name", sorted(_expected_meshes()))
def test_kept_mesh_files_load_back_exactly(name):
    path = REPO / "configs" / "meshes" / f"{name}.obj"
    assert path.stat().st_size < 300_000
    expected = _expected_meshes()[name]
    loaded = trimesh.load(path, process=False, force="mesh")
    assert loaded.vertices.shape == expected.vertices.shape
    assert np.abs(loaded.vertices - expected.vertices).max() < 1e-9
    assert np.array_equal(loaded.faces, expected.faces)
    assert loaded.is_watertight and loaded.is_volume
    assert trimesh.load(path, force="mesh").is_watertight  # also with trimesh's default processing
