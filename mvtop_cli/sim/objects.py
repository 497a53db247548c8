"""The five insertion objects of M-VTOP (paper Fig. 5) and their receptacles, built in code.

Every part is a union/difference of axis-aligned boxes, meshed on the rectilinear grid the
box faces span: the result is exactly watertight with consistent outward winding, needs no
boolean engine, and is byte-for-byte reproducible. Dimensions are written in millimetres
(``# [mm]``) where they are defined and converted to metres once, when the mesh is built.

Frames follow ``docs/frames.md``: the object frame has its origin at the centre of the face
that enters the receptacle first with +z pointing away from the receptacle; the receptacle
frame has its origin at the centre of the mouth with +z up, so the inserted object sits at
``T_receptacle_object = translation(0, 0, -insertion_depth_m)``.
"""

from __future__ import annotations

import difflib
import functools
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import trimesh

from mvtop_cli.config import ContinuousSymmetry, DirectionalClearance, PoseSpec
from mvtop_cli.errors import ConfigError

# One axis-aligned box: ((x0, x1), (y0, y1), (z0, z1)) [mm].
Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

# The receptacle floor lies this far below the inserted object's leading face (and pins end
# this far short of the cavity ceilings or more), so the nominal inserted pose is contact-free
# and "penetration" is never decided by two coplanar faces.
FLOOR_GAP_MM = 0.5  # [mm]

_RGBA = tuple[float, float, float, float]


@dataclass(frozen=True, eq=False)
class ObjectSpec:
    """One insertion object and its receptacle.

    Attributes
    ----------
    name : str
        Registry key (``cube``, ``shaft_peg``, ``plug``, ``conn1``, ``conn2``).
    description : str
        One line naming the real part this models.
    mesh : trimesh.Trimesh
        Watertight object mesh in the object frame [m]. Shared by every caller (the specs
        are cached): copy it before modifying it in place.
    receptacle_mesh : trimesh.Trimesh
        Watertight receptacle mesh in the receptacle frame [m] (shared, as ``mesh``).
    insertion_depth_m : float
        How far the object's leading face goes below the receptacle mouth when inserted [m].
    clearance_m : float
        Smallest per-side gap between object and receptacle at the inserted pose [m]: the
        lateral tolerance a pose estimate must meet for the insertion to succeed.
    grasp : (4, 4) float
        Nominal ``T_ee_object`` for the parallel gripper (fingers along ee ±y, ee +z down):
        object +z is ee −z and the finger pads sit on the object body, above the part that
        enters the receptacle, with the fingertips clear of the receptacle when inserted.
    grasp_width_m : float
        Object width between the finger pads at that grasp [m] (the finger opening that
        just touches the object).
    symmetry : (k, 4, 4) float
        Proper rigid transforms ``T_object_object'`` that map the mesh onto itself,
        identity first; rotations about the object's centre of symmetry, so some carry a
        translation in the object frame.
    color_rgba : (4,) float
        Base colour of the object in [0, 1].
    receptacle_color_rgba : (4,) float
        Base colour of the receptacle in [0, 1].
    material : str
        ``wood``, ``metal`` or ``plastic``: a hint for renderers.
    metallic, roughness : float
        PBR hints in [0, 1] for the object's material.
    continuous_symmetry : ContinuousSymmetry or None
        An axis (object frame) about which every rotation maps the mesh onto itself.
    directional_clearance : DirectionalClearance or None
        Clearance per lateral direction [m]; ``clearance_m`` is then its smallest value.
    render_mesh : trimesh.Trimesh or None
        A simplified copy of ``mesh`` (object frame [m]) for the estimator's mask renderer.
    grasp_squeeze : str
        Where the simulated pads close on the part (``object_file.GraspSpec.squeeze``):
        ``pads`` (its surface within the pads' band) or ``widest`` (its widest extent).
    """

    name: str
    description: str
    mesh: trimesh.Trimesh
    receptacle_mesh: trimesh.Trimesh
    insertion_depth_m: float
    clearance_m: float
    grasp: np.ndarray
    grasp_width_m: float
    symmetry: np.ndarray
    color_rgba: _RGBA
    receptacle_color_rgba: _RGBA
    material: str
    metallic: float
    roughness: float
    continuous_symmetry: ContinuousSymmetry | None = None
    directional_clearance: DirectionalClearance | None = None
    render_mesh: trimesh.Trimesh | None = None
    grasp_squeeze: str = "pads"

    @property
    def T_receptacle_object_inserted(self) -> np.ndarray:
        """Pose (4, 4) of the fully inserted object in the receptacle frame."""
        T = np.eye(4)
        T[2, 3] = -self.insertion_depth_m
        return T


# --------------------------------------------------------------------------- mesh building


def _box(cx: float, cy: float, sx: float, sy: float, z0: float, z1: float) -> Box:
    """Box centred at (cx, cy) in x/y with sizes (sx, sy), spanning z0..z1 [mm]."""
    return ((cx - sx / 2.0, cx + sx / 2.0), (cy - sy / 2.0, cy + sy / 2.0), (z0, z1))


def boxes_to_mesh(ops: Sequence[tuple[bool, Box]], scale: float = 1e-3) -> trimesh.Trimesh:
    """Mesh the solid made by adding (``True``) or cutting (``False``) boxes in order.

    ops : sequence of (add, ((x0, x1), (y0, y1), (z0, z1)))
        Box operations in their own units; ``scale`` converts them (mm -> m by default).

    Every box face lies on a grid plane, so the solid is a union of grid cells and its
    boundary is the set of cell faces between a filled and an empty cell. Those faces
    share grid vertices exactly (no T-junctions), which makes the surface watertight with
    outward winding by construction, provided no two filled cells touch only along an edge
    or at a corner (the callers' shapes avoid that; the tests check it).
    """
    grids = []
    for a in range(3):
        coords = np.array([c for _, box in ops for c in box[a]], dtype=np.float64)
        grids.append(np.unique(np.round(coords, 9)))
    centres = [(g[:-1] + g[1:]) / 2.0 for g in grids]
    occ = np.zeros(tuple(len(c) for c in centres), dtype=bool)
    for add, box in ops:
        inside = [(c > lo) & (c < hi) for c, (lo, hi) in zip(centres, box)]
        mask = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
        occ = occ | mask if add else occ & ~mask
    n_vert = tuple(len(g) for g in grids)

    quads = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        pad = [(1, 1) if i == a else (0, 0) for i in range(3)]
        P = np.pad(occ, pad)
        below = np.take(P, np.arange(0, occ.shape[a] + 1), axis=a)
        above = np.take(P, np.arange(1, occ.shape[a] + 2), axis=a)
        # corner offsets along (b, c); this order winds counter-clockwise seen from +a
        for faces_out, corners in (
            (below & ~above, ((0, 0), (1, 0), (1, 1), (0, 1))),
            (~below & above, ((0, 0), (0, 1), (1, 1), (1, 0))),
        ):
            idx = np.argwhere(faces_out)
            quad = np.empty((len(idx), 4), dtype=np.int64)
            for q, (db, dc) in enumerate(corners):
                corner = idx.copy()
                corner[:, b] += db
                corner[:, c] += dc
                quad[:, q] = np.ravel_multi_index(corner.T, n_vert)
            quads.append(quad)
    quads = np.concatenate(quads)
    used, inverse = np.unique(quads, return_inverse=True)
    quads = inverse.reshape(quads.shape)
    ijk = np.stack(np.unravel_index(used, n_vert), axis=1)
    vertices = np.stack([grids[a][ijk[:, a]] for a in range(3)], axis=1) * scale
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def _T(R: np.ndarray | None = None, t: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


def _about_point(R: np.ndarray, centre_m: Sequence[float]) -> np.ndarray:
    """Rigid transform (4, 4) rotating by ``R`` (3, 3) about the point ``centre_m`` [m]."""
    c = np.asarray(centre_m, dtype=np.float64)
    return _T(R, c - R @ c)


_RZ180 = np.diag([-1.0, -1.0, 1.0])
_RX180 = np.diag([1.0, -1.0, -1.0])
_RY180 = np.diag([-1.0, 1.0, -1.0])


def _cube_rotations() -> np.ndarray:
    """The 24 proper rotations (24, 3, 3) of a cube: signed permutations with det +1."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0:
                mats.append(R)
    # identity first (perm (0, 1, 2) with signs (+, +, +) is generated first)
    return np.stack(mats)


def _grasp(height_mm: float) -> np.ndarray:
    """Nominal ``T_ee_object``: object +z along ee −z, object x along ee x, the TCP (the
    midpoint between the pad centres) at object height ``height_mm`` on the object's axis."""
    return _T(_RX180, (0.0, 0.0, height_mm * 1e-3))


# --------------------------------------------------------------------------- the objects
# Each builder returns the keyword arguments of its ObjectSpec (mesh building included).
# A grasp height h puts the fingertips (pad bottom edge + 0.8 mm, see gripper.py) at object
# height h - 7.95 mm, chosen above insertion depth + FLOOR_GAP so that the fingers clear the
# receptacle mouth at the inserted pose while the pads still cover the object body.


def _cube() -> dict:
    side = 25.0  # [mm] wooden toy cube
    clearance = 0.3  # [mm] per side
    depth = 8.0  # [mm] inserted a third of its height
    block_xy, block_h = 45.0, 16.0  # [mm]
    pocket = side + 2 * clearance
    cube = boxes_to_mesh([(True, _box(0, 0, side, side, 0.0, side))])
    receptacle = boxes_to_mesh(
        [
            (True, _box(0, 0, block_xy, block_xy, -block_h, 0.0)),
            (False, _box(0, 0, pocket, pocket, -(depth + FLOOR_GAP_MM), 0.0)),
        ]
    )
    centre = (0.0, 0.0, side / 2.0 * 1e-3)
    symmetry = np.stack([_about_point(R, centre) for R in _cube_rotations()])
    return dict(
        description="25 mm wooden cube; square pocket in a wooden block, 0.3 mm clearance per side",
        mesh=cube,
        receptacle_mesh=receptacle,
        insertion_depth_m=depth * 1e-3,
        clearance_m=clearance * 1e-3,
        grasp=_grasp(16.5),
        grasp_width_m=side * 1e-3,
        symmetry=symmetry,
        color_rgba=(0.66, 0.46, 0.27, 1.0),
        receptacle_color_rgba=(0.55, 0.38, 0.22, 1.0),
        material="wood",
        metallic=0.0,
        roughness=0.8,
    )


def _shaft_peg() -> dict:
    # IndustReal rectangular_peg_12mm measures 11.957 x 7.910 x 50 mm; its tray is
    # 40 x 40 x 28 mm with a 25 mm deep hole.
    sx, sy, length = 11.96, 7.91, 50.0  # [mm]
    clearance = 0.3  # [mm] per side: 0.6 mm diametral, as the IndustReal parts
    tray_xy, tray_h, hole_depth = 40.0, 28.0, 25.0  # [mm]
    depth = hole_depth - FLOOR_GAP_MM
    peg = boxes_to_mesh([(True, _box(0, 0, sx, sy, 0.0, length))])
    tray = boxes_to_mesh(
        [
            (True, _box(0, 0, tray_xy, tray_xy, -tray_h, 0.0)),
            (False, _box(0, 0, sx + 2 * clearance, sy + 2 * clearance, -hole_depth, 0.0)),
        ]
    )
    # a plain box: D2 about its centre (the two ends are alike)
    centre = (0.0, 0.0, length / 2.0 * 1e-3)
    symmetry = np.stack([_about_point(R, centre) for R in (np.eye(3), _RZ180, _RX180, _RY180)])
    return dict(
        description="8 x 12 mm rectangular shaft peg (IndustReal-like) and its slot tray",
        mesh=peg,
        receptacle_mesh=tray,
        insertion_depth_m=depth * 1e-3,
        clearance_m=clearance * 1e-3,
        grasp=_grasp(33.0),
        grasp_width_m=sy * 1e-3,
        symmetry=symmetry,
        # brushed steel, deliberately close to the gripper's aluminium (low contrast)
        color_rgba=(0.62, 0.63, 0.65, 1.0),
        receptacle_color_rgba=(0.30, 0.31, 0.33, 1.0),
        material="metal",
        metallic=0.9,
        roughness=0.35,
    )


def _plug() -> dict:
    # NEMA 1-15P: two flat blades 6.35 wide x 1.52 thick, >= 15.88 long, 12.7 mm apart.
    blade_w, blade_t, blade_l, spacing = 6.35, 1.52, 15.9, 12.7  # [mm]
    body_x, body_y, body_h = 30.0, 22.0, 20.0  # [mm] adapter body
    clearance = 0.3  # [mm] per side around each blade
    block_x, block_y, block_h = 40.0, 34.0, 25.0  # [mm] NEMA 1-15R socket block
    depth = blade_l - FLOOR_GAP_MM  # the body face stops 0.5 mm above the socket face
    slot_depth = depth + FLOOR_GAP_MM
    plug_ops = [(True, _box(0, 0, body_x, body_y, blade_l, blade_l + body_h))]
    socket_ops = [(True, _box(0, 0, block_x, block_y, -block_h, 0.0))]
    for x in (-spacing / 2.0, spacing / 2.0):
        plug_ops.append((True, _box(x, 0, blade_t, blade_w, 0.0, blade_l)))
        socket_ops.append(
            (False, _box(x, 0, blade_t + 2 * clearance, blade_w + 2 * clearance, -slot_depth, 0.0))
        )
    symmetry = np.stack([np.eye(4), _T(_RZ180)])
    return dict(
        description="NEMA 1-15P power plug adapter and NEMA 1-15R socket",
        mesh=boxes_to_mesh(plug_ops),
        receptacle_mesh=boxes_to_mesh(socket_ops),
        insertion_depth_m=depth * 1e-3,
        clearance_m=clearance * 1e-3,
        grasp=_grasp(blade_l + body_h / 2.0),
        grasp_width_m=body_y * 1e-3,
        symmetry=symmetry,
        color_rgba=(0.93, 0.91, 0.84, 1.0),
        receptacle_color_rgba=(0.95, 0.95, 0.93, 1.0),
        material="plastic",
        metallic=0.0,
        roughness=0.5,
    )


def _connector(
    *,
    pins_xy: np.ndarray,
    housing: tuple[float, float, float],
    pin_size: float,
    key: tuple[float, float, float],
    depth: float,
    clearance: float,
    cavity_clearance: float,
    cavity_depth: float,
) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """A pin-header pair: a housing with blind pin cavities and a polarising key on its +x
    face, and a shrouded header whose pins stand on the shroud floor.

    pins_xy : (n, 2) float
        Pin centres [mm] in the object/receptacle x-y plane.
    housing : (sx, sy, height) [mm]
    key : (protrusion along +x, width along y, height) [mm] of the key rib on the +x face.
    depth : insertion depth [mm]; the shroud floor lies FLOOR_GAP_MM deeper.
    clearance : per-side gap housing/shroud and key/notch [mm].
    cavity_clearance : per-side gap pin/cavity [mm] (at least ``clearance``).
    """
    hx, hy, hh = housing
    kx, ky, kh = key
    wall, base = 1.0, 3.0  # [mm] shroud wall and header base thickness
    floor = -(depth + FLOOR_GAP_MM)
    cavity = pin_size + 2 * cavity_clearance
    housing_ops = [
        (True, _box(0, 0, hx, hy, 0.0, hh)),
        (True, ((hx / 2.0, hx / 2.0 + kx), (-ky / 2.0, ky / 2.0), (0.0, kh))),
    ]
    housing_ops += [(False, _box(x, y, cavity, cavity, 0.0, cavity_depth)) for x, y in pins_xy]
    ix, iy = hx + 2 * clearance, hy + 2 * clearance  # shroud inside
    ox, oy = ix + 2 * wall, iy + 2 * wall
    assert ox / 2.0 > hx / 2.0 + kx, "key must stay inside the shroud's footprint"
    header_ops = [
        (True, _box(0, 0, ox, oy, floor - base, 0.0)),
        (False, _box(0, 0, ix, iy, floor, 0.0)),
        # the key notch runs through the +x wall from the mouth to the floor
        (False, ((ix / 2.0, ox / 2.0), (-ky / 2.0 - clearance, ky / 2.0 + clearance), (floor, 0))),
    ]
    # pins end FLOOR_GAP_MM below the mouth: protected by the shroud, as on real headers
    header_ops += [(True, _box(x, y, pin_size, pin_size, floor, -FLOOR_GAP_MM)) for x, y in pins_xy]
    return boxes_to_mesh(housing_ops), boxes_to_mesh(header_ops)


def _conn1() -> dict:
    pitch = 3.81  # [mm] one row of 6 (pluggable terminal block style)
    pins = np.stack([(np.arange(6) - 2.5) * pitch, np.zeros(6)], axis=1)
    depth, clearance = 4.0, 0.25  # [mm]
    housing, header = _connector(
        pins_xy=pins,
        housing=(23.0, 8.0, 14.0),
        pin_size=0.8,
        key=(1.0, 3.0, 14.0),
        depth=depth,
        clearance=clearance,
        cavity_clearance=0.5,
        cavity_depth=5.0,
    )
    return dict(
        description="6-pin rectangular connector housing, 1 x 6 at 3.81 mm pitch, and its vertical header",
        mesh=housing,
        receptacle_mesh=header,
        insertion_depth_m=depth * 1e-3,
        clearance_m=clearance * 1e-3,
        grasp=_grasp(12.5),
        grasp_width_m=8.0e-3,
        symmetry=np.eye(4)[None],  # the key rib on one end breaks the 180 deg turn
        color_rgba=(0.08, 0.08, 0.09, 1.0),
        receptacle_color_rgba=(0.10, 0.10, 0.11, 1.0),
        material="plastic",
        metallic=0.0,
        roughness=0.6,
    )


def _conn2() -> dict:
    pitch = 4.14  # [mm] 2 x 3, Mini-Fit-like; rows along x, columns along y
    gx, gy = np.meshgrid([-pitch / 2.0, pitch / 2.0], [-pitch, 0.0, pitch], indexing="ij")
    pins = np.stack([gx.ravel(), gy.ravel()], axis=1)
    depth, clearance = 3.5, 0.25  # [mm]
    housing, header = _connector(
        pins_xy=pins,
        housing=(9.6, 13.0, 13.0),
        pin_size=0.64,
        key=(1.2, 3.0, 10.0),  # the latch arm
        depth=depth,
        clearance=clearance,
        cavity_clearance=0.5,
        cavity_depth=5.0,
    )
    return dict(
        description="6-pin mini connector housing, 2 x 3 at 4.14 mm pitch, and its vertical header",
        mesh=housing,
        receptacle_mesh=header,
        insertion_depth_m=depth * 1e-3,
        clearance_m=clearance * 1e-3,
        grasp=_grasp(12.0),
        grasp_width_m=13.0e-3,  # pads on the two latch-free 9.6 mm faces
        symmetry=np.eye(4)[None],  # the latch on one face breaks the 180 deg turn
        color_rgba=(0.92, 0.91, 0.86, 1.0),
        receptacle_color_rgba=(0.10, 0.10, 0.11, 1.0),
        material="plastic",
        metallic=0.0,
        roughness=0.6,
    )


_BUILDERS: dict[str, Callable[[], dict]] = {
    "cube": _cube,
    "shaft_peg": _shaft_peg,
    "plug": _plug,
    "conn1": _conn1,
    "conn2": _conn2,
}


def list_objects() -> list[str]:
    """Names of the available objects, in the paper's order (Fig. 5, left to right)."""
    return list(_BUILDERS)


@functools.lru_cache(maxsize=None)
def get_object(name: str) -> ObjectSpec:
    """The object ``name`` with its receptacle; built once, then cached and shared.

    Built as any object file is (``object_file.object_spec``), from its description
    (:func:`builtin_description`). Raises ConfigError naming the valid objects (with a
    suggestion) for an unknown name.
    """
    from .object_file import object_spec

    desc, mesh, receptacle = builtin_description(name)
    return object_spec(desc, mesh, receptacle, f"built-in object {name!r}")


def builtin_object_file(name: str, mesh_dir: str = "../meshes"):
    """The object file (``ObjectFile``) of the built-in object ``name`` with its meshes named
    ``{mesh_dir}/{name}.obj`` and ``{mesh_dir}/{name}_receptacle.obj`` (``configs/objects/``)."""
    from dataclasses import replace

    desc = builtin_description(name)[0]
    return replace(desc, object=replace(desc.object, mesh=Path(f"{mesh_dir}/{name}.obj")),
                   receptacle=replace(desc.receptacle, mesh=Path(f"{mesh_dir}/{name}_receptacle.obj")))


def builtin_description(name: str):
    """``(ObjectFile, mesh, receptacle_mesh)`` of the built-in object ``name``: the description
    ``configs/objects/<name>.yaml`` holds, with the meshes (already in mvtop's frames) it names."""
    from .object_file import Appearance, GraspSpec, ObjectFile, PartMesh, SymmetrySpec

    if name not in _BUILDERS:
        close = difflib.get_close_matches(str(name), list(_BUILDERS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        valid = ", ".join(_BUILDERS)
        raise ConfigError(f"unknown object {name!r}{hint}; valid objects: {valid}")
    f = _BUILDERS[name]()
    grasp = np.asarray(f["grasp"], dtype=np.float64)
    assert np.array_equal(grasp[:3, :3], _RX180) and not grasp[:2, 3].any(), "built-in grasps are on the axis"
    desc = ObjectFile(
        name=name,
        description=f["description"],
        object=PartMesh(mesh=Path(f"{name}.obj")),
        receptacle=PartMesh(mesh=Path(f"{name}_receptacle.obj")),
        insertion_depth_m=f["insertion_depth_m"],
        clearance_m=f["clearance_m"],
        # the sample logs were simulated with the pads centred on the widest extent
        grasp=GraspSpec(height_m=float(grasp[2, 3]), width_m=f["grasp_width_m"], squeeze="widest"),
        symmetries=SymmetrySpec(discrete=tuple(PoseSpec.from_matrix(S) for S in f["symmetry"][1:])),
        appearance=Appearance(color_rgba=f["color_rgba"], receptacle_color_rgba=f["receptacle_color_rgba"],
                              material=f["material"], metallic=f["metallic"], roughness=f["roughness"]),
    )
    return desc, f["mesh"], f["receptacle_mesh"]
