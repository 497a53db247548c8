"""``mvtop mesh-check``: check a part's CAD (and its receptacle's) for what goes wrong when
bringing one's own part, and describe it as an object file (``sim/object_file.py``).

Findings, one line each: the units read off the size, watertightness and the repairs made
(vertices split at texture seams merged), the face count with a simplified copy for the
renderer when the mesh is finer than it needs (and how far that copy is from the original),
the proper symmetries found numerically (discrete, and continuous about an axis), and, with
the receptacle, the insertion depth and the clearance per direction measured from the pair
at the inserted pose.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh

from ..config import ContinuousSymmetry, DirectionalClearance, PoseSpec
from ..contact.surface_distance import all_within, distances
from ..errors import ConfigError, MeshError
from ..io.meshes import load_mesh
from .object_file import FACES, GraspSpec, ObjectFile, PartMesh, SymmetrySpec, frame_transform, snap

# A part held in a parallel gripper is 0.5 mm to 1 m across: read as metres, a mesh more than
# 1 unit across is in millimetres (a 50 mm peg is 50 units).
_MAX_PART_M = 1.0
FLOOR_GAP_M = 0.5e-3  # the nominal inserted pose stops this short of touching (as the built-in parts)
_SAMPLES = 1500  # surface points tested per symmetry candidate / per clearance direction
_SEED = 0
_GENERIC_ANGLES_DEG = (37.0, 113.0)  # a continuous symmetry must map these onto the mesh too
_ORDERS = (3, 5, 6, 8, 12)  # n-fold rotations tested beyond the cube group's 2- and 4-fold ones


@dataclass(frozen=True)
class CheckOptions:
    units: str = "auto"  # m | mm | auto (from the size)
    leading_face: str = "-z"  # the object mesh's face that enters first (or "cad")
    mouth: str = "+z"  # the receptacle mesh's face that holds the mouth (or "cad")
    max_faces: int = 5000  # finer meshes get a simplified copy for the renderer
    symmetry_tolerance_m: float = 2e-5
    name: str | None = None


@dataclass
class CheckResult:
    findings: list[str]
    description: ObjectFile
    render_mesh: trimesh.Trimesh | None  # the simplified copy, object mesh coordinates [m]


def guess_units(extent: float) -> tuple[str, str]:
    """``(units, finding)`` from the largest extent of a mesh in its file units."""
    if extent > _MAX_PART_M:
        return "mm", (f"units: mm: the part is {extent:.4g} file units across, {extent:.4g} m if read as metres "
                      f"(too large for a gripper), {extent:.4g} mm as millimetres")
    return "m", (f"units: m: the part is {extent:.4g} file units across, {1e3 * extent:.4g} mm as metres "
                 f"({extent:.4g} mm if read as millimetres: too small for a gripper)")


def _load(path: Path, units: str, what: str, findings: list[str]) -> tuple[trimesh.Trimesh, str]:
    raw = load_mesh(path, "m", what)  # as read, file units
    extent = float(np.max(raw.extents))
    if units == "auto":
        units, line = guess_units(extent)
        findings.append(f"{what}: {line}")
    notes: list[str] = []
    try:
        mesh = load_mesh(path, units, what, closed=True, notes=notes)
    except MeshError as err:
        findings.append(f"{what}: NOT USABLE: {err}")
        raise
    if notes:
        repaired = "; ".join(n.split(": ", 1)[1] for n in notes)
        findings.append(f"{what}: {repaired} (mvtop repairs it when loading)")
    else:
        findings.append(f"{what}: watertight, {len(mesh.faces)} faces")
    return mesh, units


def simplify(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """A copy with at most ``max_faces`` faces by vertex clustering: vertices merged per cube
    of a grid (their mean), collapsed faces dropped; the cell is the largest that keeps the
    face count under the limit (bisection on its size). For rendering masks: the silhouette
    moves by at most about a cell (measured by :func:`simplification_error`)."""
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    lo = V.min(axis=0)

    def cluster(h: float) -> trimesh.Trimesh:
        keys = np.floor((V - lo) / h).astype(np.int64)
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        counts = np.bincount(inv)
        W = np.stack([np.bincount(inv, weights=V[:, a]) for a in range(3)], axis=1) / counts[:, None]
        G = inv[F]
        keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 0] != G[:, 2])
        m = trimesh.Trimesh(W, G[keep], process=False)
        m.update_faces(m.unique_faces())
        m.remove_unreferenced_vertices()
        return m

    small, large = 1e-7, float(np.max(mesh.extents))
    best = None
    for _ in range(30):
        h = np.sqrt(small * large)
        m = cluster(h)
        if len(m.faces) <= max_faces:
            best, large = m, h
        else:
            small = h
    return best if best is not None else cluster(large)


def simplification_error(original: trimesh.Trimesh, simplified: trimesh.Trimesh) -> float:
    """Largest distance [m] from points of the original surface (vertices and samples) to the
    simplified one."""
    pts = np.concatenate([_samples(original), original.vertices[:: max(1, len(original.vertices) // 2000)]])
    return float(distances(simplified.vertices, simplified.faces, pts).max())


def _samples(mesh: trimesh.Trimesh, n: int = _SAMPLES) -> np.ndarray:
    from ..eval.metrics import sample_surface

    return sample_surface(mesh.vertices, mesh.faces, n, np.random.default_rng(_SEED))


def _about(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c
    return T


def _axis_rotation(axis: int, deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz"[axis], deg, degrees=True).as_matrix()
    return snap(np.pad(R, ((0, 1), (0, 1))))[:3, :3]


def find_symmetries(mesh: trimesh.Trimesh, tol_m: float) -> tuple[list[np.ndarray], ContinuousSymmetry | None]:
    """Proper rigid symmetries of ``mesh`` (object frame, metres) about its centre of mass:
    ``(discrete (k, 4, 4) besides the identity, continuous or None)``.

    Candidates are rotations about the centre of mass whose axes are the frame's axes: the 24
    of the cube group (signed permutations), and 3-, 5-, 6-, 8- and 12-fold turns about each
    axis. A candidate is a symmetry when every test point (surface samples and vertices)
    lands within ``tol_m`` of the surface (exact point-triangle distances); as the transform
    keeps the area, that makes the mesh its own image. An axis about which two generic angles
    (37 and 113 degrees) pass is a continuous symmetry; the discrete ones then keep one turn
    that reverses the axis (the others differ from it by a turn about the axis).
    """
    c = np.asarray(mesh.center_mass if mesh.is_volume else mesh.bounds.mean(axis=0), dtype=np.float64)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(_SEED)
    verts = V[rng.permutation(len(V))[:500]]
    pts = np.concatenate([_samples(mesh), verts])

    def symmetric(T: np.ndarray) -> bool:
        return all_within(V, F, pts @ T[:3, :3].T + T[:3, 3], tol_m)

    continuous = None
    for a in range(3):
        if all(symmetric(_about(_axis_rotation(a, d), c)) for d in _GENERIC_ANGLES_DEG):
            axis = np.zeros(3)
            axis[a] = 1.0
            continuous = ContinuousSymmetry(axis=tuple(axis), point_m=tuple(round(float(v), 9) for v in c))
            break
    candidates = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0 and not np.array_equal(R, np.eye(3)):
                candidates.append(R)
    for a in range(3):
        for n in _ORDERS:
            candidates += [_axis_rotation(a, 360.0 * k / n) for k in range(1, n) if (360.0 * k / n) % 90.0]
    found = []
    for R in candidates:
        if continuous is not None:
            e = np.asarray(continuous.axis)
            if np.allclose(R @ e, e):  # a turn about the continuous axis: already in the group
                continue
            if found:  # one axis-reversing turn stands for all of them
                break
        T = _about(R, c)
        if symmetric(T):
            T[:3, 3] = np.round(T[:3, 3], 9)  # [m]: 1 nm, far below any tolerance
            found.append(T)
    return found, continuous


def free_travel(obj: trimesh.Trimesh, rec: trimesh.Trimesh, T_rec_obj: np.ndarray, direction: np.ndarray) -> float:
    """How far [m] the object (at ``T_rec_obj`` in the receptacle frame) moves along
    ``direction`` (receptacle frame) before it touches the receptacle: the nearest hit of rays
    from the object's surface points along ``direction`` on the receptacle and of rays from
    the receptacle's points (near the object) against it on the object; inf if none."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    obj_pts = trimesh.transformations.transform_points(np.concatenate([obj.vertices, _samples(obj, 4 * _SAMPLES)]),
                                                       T_rec_obj)
    lo, hi = obj_pts.min(axis=0) - 0.005, obj_pts.max(axis=0) + 0.005
    rec_pts = np.concatenate([rec.vertices, _samples(rec, 8 * _SAMPLES)])
    rec_pts = rec_pts[np.all((rec_pts >= lo) & (rec_pts <= hi), axis=1)]
    best = np.inf
    hits, rays, _ = rec.ray.intersects_location(obj_pts, np.tile(d, (len(obj_pts), 1)), multiple_hits=False)
    if len(hits):
        best = min(best, float(np.min(np.einsum("ij,j->i", hits - obj_pts[rays], d))))
    if len(rec_pts):
        moved = obj.copy()
        moved.apply_transform(T_rec_obj)
        hits, rays, _ = moved.ray.intersects_location(rec_pts, np.tile(-d, (len(rec_pts), 1)), multiple_hits=False)
        if len(hits):
            best = min(best, float(np.min(np.einsum("ij,j->i", rec_pts[rays] - hits, d))))
    return best


def measure_fit(obj: trimesh.Trimesh, rec: trimesh.Trimesh, findings: list[str]) -> dict | None:
    """Insertion depth and clearance per direction from the pair (mvtop frames, metres): the
    object is lowered from 2 mm above the mouth until it touches; the inserted pose stops
    ``FLOOR_GAP_M`` short of that; there it is centred between the walls (the offset is
    reported) and its free travel along +-x and +-y is the clearance. None when it does not
    enter the receptacle at the mouth's centre."""
    start = 0.002
    T = np.eye(4)
    T[2, 3] = start
    down = free_travel(obj, rec, T, [0.0, 0.0, -1.0])
    depth_contact = down - start
    if not np.isfinite(down) or depth_contact < 2 * FLOOR_GAP_M:
        findings.append(f"insertion: the part lowered onto the centre of the receptacle's mouth touches "
                        f"{1e3 * -depth_contact:.3g} mm above it: it does not go in there; move the receptacle mesh "
                        "(receptacle.pose) so the bore is at the origin, then run mesh-check again")
        return None
    depth = depth_contact - FLOOR_GAP_M
    T[2, 3] = -depth
    offset = np.zeros(2)
    for _ in range(3):
        travel = [free_travel(obj, rec, T, v) for v in ([-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0])]
        shift = np.array([(travel[1] - travel[0]) / 2.0, (travel[3] - travel[2]) / 2.0])
        if not np.all(np.isfinite(shift)) or np.max(np.abs(shift)) < 1e-6:
            break
        offset += shift
        T[:2, 3] = offset
    findings.append(f"insertion: the leading face goes {1e3 * depth_contact:.4g} mm below the mouth before it touches; "
                    f"insertion_depth_m {depth:.6g} stops {1e3 * FLOOR_GAP_M:g} mm short of that")
    if not all(np.isfinite(travel)):
        findings.append("clearance: the part moves freely sideways at the inserted pose (no wall within reach): "
                        "set clearance_m yourself")
        return {"depth": depth, "offset": offset, "travel": None}
    if np.max(np.abs(offset)) > 1e-6:
        findings.append(f"insertion: the bore's centre is at ({1e3 * offset[0]:.4g}, {1e3 * offset[1]:.4g}) mm from "
                        "the mouth face's centre; receptacle.pose moves it to the origin")
    findings.append("clearance (free travel at the inserted pose) [mm]: "
                    + ", ".join(f"{n} {1e3 * t:.3f}" for n, t in zip(("-x", "+x", "-y", "+y"), travel, strict=True)))
    return {"depth": depth, "offset": offset, "travel": travel}


def check(mesh_path: Path, receptacle_path: Path | None, options: CheckOptions = CheckOptions()) -> CheckResult:
    """Run every check on the part (and its receptacle) and describe them as an object file."""
    findings: list[str] = []
    mesh_path = Path(mesh_path)
    if options.leading_face not in FACES + ("cad",) or options.mouth not in FACES + ("cad",):
        raise MeshError(f"faces are named {', '.join(FACES)} or cad, got {options.leading_face!r}/{options.mouth!r}")
    raw, units = _load(mesh_path, options.units, "object mesh", findings)
    part = PartMesh(mesh=mesh_path.resolve(), units=units, frame=options.leading_face)
    T_obj = frame_transform(raw, part, "-z")
    obj = raw.copy()
    obj.apply_transform(T_obj)
    e = obj.extents
    findings.append(f"object frame: {options.leading_face} face enters first; the part is {1e3 * e[0]:.4g} x "
                    f"{1e3 * e[1]:.4g} x {1e3 * e[2]:.4g} mm (x, y, z), origin at that face's centre"
                    if options.leading_face != "cad" else "object frame: as in the CAD file")
    render = None
    if len(obj.faces) > options.max_faces:
        render = simplify(raw, options.max_faces)
        err = simplification_error(raw, render)
        findings.append(f"faces: {len(obj.faces)}, more than the renderer needs ({options.max_faces}): a copy with "
                        f"{len(render.faces)} faces is at most {1e3 * err:.3f} mm from the original surface "
                        "(object.render_mesh)")
    else:
        findings.append(f"faces: {len(obj.faces)} (<= {options.max_faces}: fine for the renderer)")
    discrete, continuous = find_symmetries(obj, options.symmetry_tolerance_m)
    group = len(discrete) + 1
    if continuous is not None:
        ax = "xyz"[int(np.argmax(np.abs(continuous.axis)))]
        findings.append(f"symmetries: continuous about the object's {ax} axis through "
                        f"({', '.join(f'{1e3 * v:.4g}' for v in continuous.point_m)}) mm"
                        + (", and a turn that reverses it" if discrete else ""))
    else:
        findings.append(f"symmetries: {group} proper symmetries (identity included), within "
                        f"{1e3 * options.symmetry_tolerance_m:g} mm")
    desc = ObjectFile(
        name=options.name or mesh_path.stem, object=part, receptacle=PartMesh(mesh=mesh_path.resolve()),
        insertion_depth_m=0.0, clearance_m=0.0003,
        symmetries=SymmetrySpec(discrete=tuple(PoseSpec.from_matrix(S) for S in discrete), continuous=continuous),
    )
    if receptacle_path is not None:
        rec_raw, rec_units = _load(Path(receptacle_path), options.units, "receptacle mesh", findings)
        rpart = PartMesh(mesh=Path(receptacle_path).resolve(), units=rec_units, frame=options.mouth)
        rec = rec_raw.copy()
        rec.apply_transform(frame_transform(rec_raw, rpart, "+z"))
        fit = measure_fit(obj, rec, findings)
        if fit is not None:
            if np.max(np.abs(fit["offset"])) > 1e-6:
                rpart = replace(rpart, pose=PoseSpec(xyz_m=(-float(fit["offset"][0]), -float(fit["offset"][1]), 0.0)))
            desc = replace(desc, receptacle=rpart, insertion_depth_m=round(float(fit["depth"]), 9))
            t = fit["travel"]
            if t is not None:
                clearance = round(float(min(t)), 9)
                desc = replace(desc, clearance_m=clearance)
                if max(t) - min(t) > max(2e-5, 0.1 * min(t)):
                    desc = replace(desc, directional_clearance=DirectionalClearance(
                        x_m=(round(t[0], 9), round(t[1], 9)), y_m=(round(t[2], 9), round(t[3], 9))))
                    findings.append(f"clearance: differs by direction: directional_clearance written, clearance_m "
                                    f"{1e3 * clearance:.3f} mm its smallest")
        else:
            desc = replace(desc, receptacle=rpart)
    else:
        findings.append("receptacle: none given (--receptacle): insertion depth and clearance not measured; "
                        "receptacle.mesh is a placeholder to replace")
    try:
        from .object_file import object_spec

        spec = object_spec(desc, raw, raw if receptacle_path is None else rec_raw, mesh_path)
        findings.append(f"grasp: TCP {1e3 * spec.grasp[2, 3]:.4g} mm above the leading face (the lowest whose "
                        f"fingertips clear the receptacle), {1e3 * spec.grasp_width_m:.4g} mm between the pads there")
        desc = replace(desc, grasp=GraspSpec(height_m=round(float(spec.grasp[2, 3]), 9)))
    except ConfigError as err:  # reported as a finding; the file is still written
        findings.append(f"grasp: {err}")
    return CheckResult(findings, desc, render)


def write_result(result: CheckResult, out: Path | None) -> str:
    """The object file's text (the findings as comment lines at its top); with ``out``, also
    written there, with the renderer's simplified copy beside it (``<out stem>_render.obj``,
    the object mesh's file units and coordinates)."""
    from ..io.meshes import UNIT_SCALE, write_obj
    from .object_file import object_file_dict

    desc = result.description
    if out is not None and result.render_mesh is not None:
        render_path = Path(out).with_name(f"{Path(out).stem}_render.obj")
        copy = result.render_mesh.copy()
        copy.apply_scale(1.0 / UNIT_SCALE[desc.object.units])
        write_obj(copy, render_path, f"{desc.name} render copy")
        desc = replace(desc, object=replace(desc.object, render_mesh=render_path.resolve()))
    import yaml

    base = Path(out).resolve().parent if out is not None else None
    header = "".join(f"# {line}\n" for line in ["mvtop object file written by mvtop mesh-check; findings:"]
                     + [f"- {f}" for f in result.findings])
    text = header + yaml.safe_dump(object_file_dict(desc, base), sort_keys=False, default_flow_style=None)
    if out is not None:
        from ..io.atomic import atomic_output

        with atomic_output(Path(out)) as fh:
            fh.write(text.encode())
    return text
