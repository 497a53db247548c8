"""Mesh files: load (OBJ, STL, PLY, ... through trimesh) with unit handling, and write OBJ."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..errors import MeshError
from .atomic import atomic_output

UNIT_SCALE = {"m": 1.0, "mm": 1e-3}
_DIGITS = 10  # decimals of a metre in written OBJ files: 0.1 nm, far below any tolerance


def load_mesh(
    path: str | Path, units: str = "m", what: str = "mesh", *, closed: bool | None = None,
    notes: list[str] | None = None,
) -> trimesh.Trimesh:
    """Load a triangle mesh and scale it to metres; one-line ``MeshError`` on any failure.

    closed : bool or None
      None: the mesh as read. True: it must be watertight (a signed distance, the tactile
      penetration render need its inside and outside); a mesh that is not, or has
      degenerate or duplicate faces or inconsistent winding, is repaired
      (``repair_mesh``), and refused with a ``MeshError`` naming the file when the repair
      does not close it. False: repaired the same way where needed, and used open if the
      repair cannot close it.
    notes : list of str, optional
      Receives one line per repaired mesh (which repairs) and per mesh left open.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: {what} file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many types for malformed files
        raise MeshError(f"{path}: cannot read {what} ({type(err).__name__}: {err})") from err
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{path}: {what} has no triangles")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{path}: {what} has non-finite vertex coordinates")
    mesh = loaded.copy()
    if closed is not None and mesh_defects(mesh):
        defects = mesh_defects(mesh)
        mesh, repairs = repair_mesh(mesh)
        if mesh.is_watertight:
            if notes is not None:
                notes.append(f"{path}: {what} {', '.join(defects)}; repaired ({', '.join(repairs)}), now watertight")
        elif closed:
            raise MeshError(
                f"{path}: {what} is not watertight ({_count(_open_edges(mesh), 'open edge')} left after "
                f"{', '.join(repairs) or 'trying to repair it'}); the contact signed distance and the tactile "
                "rendering need its inside and outside: close the mesh"
            )
        elif notes is not None:
            notes.append(f"{path}: {what} is not watertight ({_count(_open_edges(mesh), 'open edge')} after repair); "
                         "used as it is (it only occludes)")
    mesh.apply_scale(UNIT_SCALE[units])
    return mesh


def mesh_defects(mesh: trimesh.Trimesh) -> list[str]:
    """What keeps ``mesh`` from being a clean closed surface (empty when it is one): open
    edges, degenerate (zero-area) faces, duplicate faces, inconsistent winding, inward normals."""
    out = []
    if not mesh.is_watertight:
        out.append(f"is not watertight ({_count(_open_edges(mesh), 'open edge')})")
    degenerate = int(np.sum(~mesh.nondegenerate_faces()))
    if degenerate:
        out.append(f"has {_count(degenerate, 'degenerate face')}")
    duplicate = len(mesh.faces) - len(mesh.unique_faces().nonzero()[0])
    if duplicate:
        out.append(f"has {_count(duplicate, 'duplicate face')}")
    if mesh.is_watertight and not mesh.is_winding_consistent:
        out.append("has inconsistent face winding")
    elif mesh.is_watertight and mesh.volume < 0:
        out.append("has inward-facing normals")
    return out


def repair_mesh(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, list[str]]:
    """A repaired copy of ``mesh`` (geometry only) and the repairs made, in this order:
    vertices merged by position (also those split at texture or normal seams), degenerate
    and duplicate faces removed, unused vertices dropped, faces wound consistently and
    outwards, then small (triangle and quad) holes filled."""
    m = trimesh.Trimesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), process=False)
    repairs = []
    n = len(m.vertices)
    m.merge_vertices()
    if len(m.vertices) < n:
        repairs.append(f"merged {_count(n - len(m.vertices), 'coincident vertex', 'coincident vertices')}")
    n = len(m.faces)
    m.update_faces(m.nondegenerate_faces())
    if len(m.faces) < n:
        repairs.append(f"removed {_count(n - len(m.faces), 'degenerate face')}")
    n = len(m.faces)
    m.update_faces(m.unique_faces())
    if len(m.faces) < n:
        repairs.append(f"removed {_count(n - len(m.faces), 'duplicate face')}")
    m.remove_unreferenced_vertices()
    if not m.is_watertight:
        n = len(m.faces)
        trimesh.repair.fill_holes(m)
        if len(m.faces) > n:
            repairs.append(f"filled holes with {_count(len(m.faces) - n, 'face')}")
    flipped = not m.is_winding_consistent or (m.is_watertight and m.volume < 0)
    trimesh.repair.fix_normals(m)
    if flipped:
        repairs.append("wound the faces consistently outwards")
    return m, repairs


def _count(n: int, word: str, plural: str | None = None) -> str:
    return f"{n} {word if n == 1 else plural or word + 's'}"


def _open_edges(mesh: trimesh.Trimesh) -> int:
    """Edges used by one face only (0 for a closed surface)."""
    return int(len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)))


def obj_text(mesh: trimesh.Trimesh, name: str) -> str:
    """OBJ text of ``mesh``: vertices [m] and faces only, vertex order kept, deterministic."""
    return trimesh.exchange.obj.export_obj(
        mesh, include_normals=False, include_color=False, include_texture=False, digits=_DIGITS,
        header=f"mvtop {name}, units: metres",
    )


def write_obj(mesh: trimesh.Trimesh, path: str | Path, name: str | None = None) -> Path:
    """Write ``mesh`` as OBJ to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_output(path) as fh:
        fh.write(obj_text(mesh, name or path.stem).encode("ascii"))
    return path
