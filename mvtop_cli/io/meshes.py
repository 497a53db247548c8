"""Mesh files: load (OBJ, STL, PLY, ... through trimesh) with unit handling, and write OBJ."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from ..errors import MeshError
from .atomic import atomic_output

UNIT_SCALE = {"m": 1.0, "mm": 1e-3}
_DIGITS = 10  # decimals of a metre in written OBJ files: 0.1 nm, far below any tolerance


def load_mesh(path: str | Path, units: str = "m", what: str = "mesh") -> trimesh.Trimesh:
    """Load a triangle mesh and scale it to metres; one-line ``MeshError`` on any failure."""
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
    mesh.apply_scale(UNIT_SCALE[units])
    return mesh


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
