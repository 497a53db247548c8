"""Object files: one YAML file describes an insertion part and its receptacle for ``mvtop simulate``,
``mvtop benchmark accuracy`` and the estimate config they write.

The file gives the two meshes with their units and frames, the grasp, the clearance (per side
or per direction), the insertion depth, the symmetries (discrete, and continuous about an
axis) and the colours. It is validated like the config (``config.parse_section``: unknown
keys with a suggestion, types, ranges, one ``ConfigError`` naming the file and dotted key).
The five built-in objects are the same descriptions, built in code (``sim/objects.py``) and
written as files by ``scripts/make_samples.py`` into ``configs/objects/``.

Frames (docs/frames.md): the object frame has its origin at the centre of the face that enters
the receptacle first and +z pointing away from the receptacle; the receptacle frame has its
origin at the centre of the mouth and +z up; inserted, ``T_receptacle_object =
translation(0, 0, -insertion_depth_m)``. A mesh is given in that frame (``frame: cad``), or
its frame is derived from the face of its bounding box that enters first (object) or holds
the mouth (receptacle), ``frame: -z`` etc.: the mesh is turned so that face points along
-z (object) or +z (receptacle) and moved so the face's centre is the origin; ``pose`` then
moves it further (e.g. to a bore that is not at the centre of the receptacle's box).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

from ..config import ContinuousSymmetry, DirectionalClearance, PoseSpec, invalid, parse_section
from ..errors import ConfigError

FACES = ("-x", "+x", "-y", "+y", "-z", "+z")
# The receptacle floor (or the stop) lies this far beyond the inserted part by default, so the
# nominal inserted pose is contact-free (as FLOOR_GAP_MM of the built-in parts).
_FINGERTIP_GAP_M = 0.5e-3  # fingertips this far above the receptacle mouth at the inserted pose
_SNAP = 1e-12  # rotation entries this close to 0 or +-1 are made exact (rpy round trips)


def _range(lo: float, hi: float, doc: str = "", lo_open: bool = False) -> dict:
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "doc": doc}


@dataclass(frozen=True)
class PartMesh:
    """One mesh file and how its coordinates relate to mvtop's frame (see the module docstring)."""

    mesh: Path
    units: Literal["m", "mm"] = "m"
    frame: Literal["cad", "-x", "+x", "-y", "+y", "-z", "+z"] = "cad"
    pose: PoseSpec = PoseSpec()
    render_mesh: Path | None = field(default=None, metadata={"doc": "a simplified copy of mesh (same coordinates "
                                                                     "and units) for the estimator's renderer"})


@dataclass(frozen=True)
class GraspSpec:
    """Where the parallel gripper holds the part: the TCP (midway between the pads) on the object's
    z axis at ``height_m`` above the leading face, the pads on the object's +-y faces (``yaw_deg``
    0) or turned about the object's z axis by ``yaw_deg``; or an explicit ``pose``
    (``T_ee_object``, ee +z down, fingers along ee +-y). ``height_m`` defaults to the lowest
    grasp whose fingertips clear the receptacle at the inserted pose.

    ``squeeze`` says where the simulator's pads close on the part after each grasp offset and
    slip: ``pads`` on its surface within the pads' band (``gripper.pad_band_extent``, as
    ``width_m`` is measured), ``widest`` on its widest extent over all vertices (the built-in
    objects, whose sample logs were made that way)."""

    height_m: float | None = field(default=None, metadata=_range(0.0, 1.0))
    yaw_deg: float = field(default=0.0, metadata=_range(-360.0, 360.0))
    pose: PoseSpec | None = None
    width_m: float | None = field(default=None, metadata=_range(0.0, 0.2, lo_open=True,
                                                                doc="object width between the pads"))
    squeeze: Literal["pads", "widest"] = field(default="pads", metadata={
        "doc": "where the simulated pads close: the part's surface within their band, or its widest extent"})


@dataclass(frozen=True)
class SymmetrySpec:
    """Proper rigid transforms ``T_object_object'`` (besides the identity) that map the mesh onto
    itself, and a continuous symmetry (every rotation about an axis)."""

    discrete: tuple[PoseSpec, ...] = ()
    continuous: ContinuousSymmetry | None = None


@dataclass(frozen=True)
class Appearance:
    """Colours (RGBA in [0, 1]) and material hints for the renderer."""

    color_rgba: tuple[float, float, float, float] = field(default=(0.62, 0.63, 0.65, 1.0), metadata=_range(0.0, 1.0))
    receptacle_color_rgba: tuple[float, float, float, float] = field(default=(0.30, 0.31, 0.33, 1.0),
                                                                     metadata=_range(0.0, 1.0))
    material: Literal["wood", "metal", "plastic"] = "metal"
    metallic: float = field(default=0.9, metadata=_range(0.0, 1.0))
    roughness: float = field(default=0.35, metadata=_range(0.0, 1.0))


@dataclass(frozen=True)
class ObjectFile:
    """An object file (YAML), see the module docstring and README "Your own part"."""

    name: str
    object: PartMesh
    receptacle: PartMesh
    insertion_depth_m: float = field(metadata=_range(0.0, 0.2))
    clearance_m: float = field(metadata=_range(0.0, 0.01, lo_open=True, doc="per side; the smallest if directional"))
    description: str | None = None
    directional_clearance: DirectionalClearance | None = None
    grasp: GraspSpec = GraspSpec()
    symmetries: SymmetrySpec = SymmetrySpec()
    appearance: Appearance = Appearance()


# --------------------------------------------------------------------------- frames


def _face_rotation(face: str, towards: str) -> np.ndarray:
    """Rotation (3, 3) that turns the mesh axis ``face`` (e.g. "+z") to ``towards`` ("-z" or
    "+z"), turning about x for the y faces and about y for the x faces (right-handed)."""
    target = -1.0 if towards == "-z" else 1.0
    axis, sign = "xyz".index(face[1]), (1.0 if face[0] == "+" else -1.0)
    if axis == 2:
        return np.eye(3) if sign == target else np.diag([1.0, -1.0, -1.0])
    v = np.zeros(3)
    v[axis] = sign
    about = np.array([0.0, 1.0, 0.0]) if axis == 0 else np.array([1.0, 0.0, 0.0])
    for R in (_rot90(about, 1), _rot90(about, -1)):
        if np.allclose(R @ v, [0.0, 0.0, target]):
            return R
    raise AssertionError(face)


def _rot90(axis: np.ndarray, sign: int) -> np.ndarray:
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + sign * K + K @ K  # Rodrigues at +-90 degrees, exact


def frame_transform(mesh: trimesh.Trimesh, part: PartMesh, towards: str) -> np.ndarray:
    """``T_frame_mesh`` (4, 4): the mesh (metres) into the object frame (``towards="-z"``, the
    named face enters first) or the receptacle frame (``"+z"``, the named face holds the mouth),
    then moved by ``part.pose``."""
    T = np.eye(4)
    if part.frame != "cad":
        R = _face_rotation(part.frame, towards)
        corners = trimesh.bounds.corners(mesh.bounds) @ R.T
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        origin = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2] if towards == "-z" else hi[2]])
        T[:3, :3] = R
        T[:3, 3] = -origin
    return snap(part.pose.matrix()) @ T


def snap(T: np.ndarray) -> np.ndarray:
    """``T`` with rotation entries within 1e-12 of 0 or +-1 made exact (a 180 deg turn written as
    roll-pitch-yaw comes back with 1e-16 residues)."""
    T = np.array(T, dtype=np.float64)
    R = T[:3, :3]
    for v in (0.0, 1.0, -1.0):
        R[np.abs(R - v) < _SNAP] = v
    return T


# --------------------------------------------------------------------------- loading


def read_object_file(path: Path | str) -> ObjectFile:
    """Parse and validate an object file; ``ConfigError`` naming the file and key otherwise."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: object file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read object file ({err})") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"{path}: invalid YAML{where}: {getattr(err, 'problem', None) or err}") from None
    return parse_section(ObjectFile, data, path, path.resolve().parent)


def load_object_file(path: Path | str):
    """The ``ObjectSpec`` an object file describes: meshes loaded (watertight after repair,
    else ``MeshError``), in metres and mvtop's frames."""
    from ..io.meshes import load_mesh

    path = Path(path)
    desc = read_object_file(path)
    mesh = load_mesh(desc.object.mesh, desc.object.units, "object mesh", closed=True)
    receptacle = load_mesh(desc.receptacle.mesh, desc.receptacle.units, "receptacle mesh", closed=True)
    render = None
    if desc.object.render_mesh is not None:
        render = load_mesh(desc.object.render_mesh, desc.object.units, "object render mesh")
    return object_spec(desc, mesh, receptacle, path, render)


def object_spec(desc: ObjectFile, mesh: trimesh.Trimesh, receptacle_mesh: trimesh.Trimesh, source: Path | str,
                render_mesh: trimesh.Trimesh | None = None):
    """Build the ``ObjectSpec`` of ``desc`` from its meshes (metres, mesh coordinates): frames
    applied, grasp resolved, symmetries as matrices. The one constructor of object specs (the
    built-in objects come through here too)."""
    from ..sim.gripper import FINGERTIP_OFFSET_M
    from ..sim.objects import ObjectSpec

    T_object_mesh = frame_transform(mesh, desc.object, "-z")
    if render_mesh is not None:
        render_mesh = _moved(render_mesh, T_object_mesh)
    mesh = _moved(mesh, T_object_mesh)
    receptacle_mesh = _moved(receptacle_mesh, frame_transform(receptacle_mesh, desc.receptacle, "+z"))
    g = desc.grasp
    if g.pose is not None and g.height_m is not None:
        raise invalid(source, "grasp", "expected either height_m (and yaw_deg) or pose, not both")
    if g.pose is not None:
        grasp = snap(g.pose.matrix())
    else:
        height = g.height_m
        if height is None:
            height = desc.insertion_depth_m + _FINGERTIP_GAP_M + FINGERTIP_OFFSET_M
        top = float(mesh.bounds[1][2])
        if height > top:
            raise invalid(source, "grasp.height_m", f"expected a height on the part (<= its top at {top:.6g} m), got "
                                                    f"{height:.6g} (the default keeps the fingertips above the "
                                                    "receptacle: a part this short needs a smaller insertion depth)")
        grasp = _grasp(height, g.yaw_deg)
    width = g.width_m if g.width_m is not None else pad_width(mesh, grasp)
    sym = [np.eye(4)] + [snap(s.matrix()) for s in desc.symmetries.discrete]
    cont = desc.symmetries.continuous
    if cont is not None and np.linalg.norm(cont.axis) < 1e-6:
        raise invalid(source, "symmetries.continuous.axis", "expected a non-zero direction")
    dc = desc.directional_clearance
    if dc is not None and abs(min(*dc.x_m, *dc.y_m) - desc.clearance_m) > 1e-9:
        raise invalid(source, "clearance_m", f"expected the smallest value of directional_clearance, "
                                             f"{min(*dc.x_m, *dc.y_m)!r}, got {desc.clearance_m!r}")
    a = desc.appearance
    symmetry = np.stack(sym)
    symmetry.setflags(write=False)
    grasp.setflags(write=False)
    return ObjectSpec(
        name=desc.name, description=desc.description or desc.name, mesh=mesh, receptacle_mesh=receptacle_mesh,
        insertion_depth_m=desc.insertion_depth_m, clearance_m=desc.clearance_m, grasp=grasp, grasp_width_m=width,
        symmetry=symmetry, color_rgba=a.color_rgba, receptacle_color_rgba=a.receptacle_color_rgba,
        material=a.material, metallic=a.metallic, roughness=a.roughness, continuous_symmetry=cont,
        directional_clearance=dc, render_mesh=render_mesh, grasp_squeeze=g.squeeze,
    )


def _moved(mesh: trimesh.Trimesh, T: np.ndarray) -> trimesh.Trimesh:
    if np.array_equal(T, np.eye(4)):
        return mesh
    out = mesh.copy()
    out.apply_transform(T)
    return out


def _grasp(height_m: float, yaw_deg: float) -> np.ndarray:
    """``T_ee_object``: object +z along ee -z, the object turned by ``yaw_deg`` about its z axis
    (0: object x along ee x, pads on the object's +-y faces), TCP at ``height_m`` on the axis."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    if yaw_deg != 0.0:
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        T[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T = snap(T)
    T[:3, 3] = (0.0, 0.0, height_m)
    return T


def pad_width(mesh: trimesh.Trimesh, T_ee_object: np.ndarray) -> float:
    """The part's width [m] along ee y between the gel pads' edges (``gripper.pad_band_extent``):
    the finger opening that just touches the part where the pads hold it, not its widest
    extent elsewhere (a flange above or below the pads)."""
    from ..sim.gripper import pad_band_extent

    extent = pad_band_extent(mesh.vertices, mesh.edges_unique, T_ee_object)
    if extent is None:
        raise ConfigError("the gripper's pads do not reach the part at the grasp (grasp.height_m or grasp.pose)")
    return extent[1] - extent[0]


def resolve_object(ref):
    """An ``ObjectSpec`` from a built-in object's name, an object file's path (``Path``, or a
    string ending in .yaml or .yml) or a spec (returned as it is)."""
    from ..sim.objects import ObjectSpec, get_object

    if isinstance(ref, ObjectSpec):
        return ref
    if isinstance(ref, Path) or str(ref).endswith((".yaml", ".yml")):
        return _load_cached(str(Path(ref).resolve()), Path(ref).stat().st_mtime_ns if Path(ref).exists() else 0)
    return get_object(ref)


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int):
    del mtime_ns  # part of the cache key: an edited file is read again
    return load_object_file(path)


def object_file_dict(desc: ObjectFile, relative_to: Path | None = None) -> dict:
    """``desc`` as YAML-ready data (keys in the order of the dataclasses; paths relative to
    ``relative_to`` when given), leaving out what is at its default."""
    import dataclasses
    import os

    def conv(v):
        if dataclasses.is_dataclass(v):
            out = {}
            for f in dataclasses.fields(v):
                x = getattr(v, f.name)
                if f.default is not dataclasses.MISSING and _same(x, f.default):
                    continue
                out[f.name] = conv(x)
            return out
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        if isinstance(v, Path):
            return os.path.relpath(v, relative_to) if relative_to is not None and v.is_absolute() else v.as_posix()
        if isinstance(v, float):
            return round(v, 12) + 0.0  # no -0.0 in the file
        return v

    return conv(desc)


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except ValueError:
        return False


def write_object_file(desc: ObjectFile, path: Path, header: str = "") -> Path:
    """Write ``desc`` as YAML to ``path`` (atomically); mesh paths as ``desc`` gives them."""
    import yaml

    from ..io.atomic import atomic_output

    text = header + yaml.safe_dump(object_file_dict(desc), sort_keys=False, default_flow_style=None)
    with atomic_output(Path(path)) as fh:
        fh.write(text.encode())
    return Path(path)
