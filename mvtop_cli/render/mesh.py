"""Triangle meshes as the renderers hold them: validated arrays plus the convex hull used for ROIs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from mvtop_cli.errors import MeshError


@dataclass(frozen=True)
class RenderMesh:
    """One registered mesh.

    vertices : (V, 3) float64, in the mesh frame [m]
    faces : (F, 3) int32, indices into ``vertices``
    hull_vertices : (H, 3) float64, vertices of the convex hull [m]; the projected
        bounds of the hull equal those of the mesh, at a fraction of the cost
    hull_edges : (E, 2) int32, edges of the hull, for clipping it at the gel plane
    closed : bool, watertight with consistent outward winding, so that back faces
        can be culled without changing any mask or depth
    face_planes : (F, 4) float64, per face ``(n, n . v0)`` with ``n = (v1 - v0) x (v2 - v0)``
        (unnormalised, outward for a closed mesh); a face faces a viewpoint ``c`` in the
        mesh frame when ``n . c > n . v0``
    """

    vertices: np.ndarray
    faces: np.ndarray
    hull_vertices: np.ndarray
    hull_edges: np.ndarray
    closed: bool
    face_planes: np.ndarray

    @staticmethod
    def from_arrays(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> "RenderMesh":
        """Validate ``vertices`` (V, 3) [m] and ``faces`` (F, 3) and precompute the hull.

        Raises :class:`MeshError` naming ``name`` when the mesh is empty, has
        non-finite vertices or faces that index outside ``vertices``.
        """
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
            raise MeshError(f"{name}: vertices must be (V >= 3, 3), got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) < 1:
            raise MeshError(f"{name}: faces must be (F >= 1, 3), got shape {f.shape}")
        if not np.all(np.isfinite(v)):
            raise MeshError(f"{name}: {int(np.sum(~np.isfinite(v)))} non-finite vertex coordinates")
        if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
            raise MeshError(f"{name}: face indices must be integers in [0, {len(v) - 1}]")
        f = np.ascontiguousarray(f, dtype=np.int32)
        tm = trimesh.Trimesh(vertices=v, faces=f, process=False)
        with np.errstate(invalid="ignore", divide="ignore"):
            return RenderMesh._build(tm, v, f, name)

    @staticmethod
    def _build(tm: trimesh.Trimesh, v: np.ndarray, f: np.ndarray, name: str) -> "RenderMesh":
        if tm.area <= 0.0:
            raise MeshError(f"{name}: all {len(f)} faces are degenerate (zero area)")
        try:
            hull = tm.convex_hull
            hull_v = np.ascontiguousarray(hull.vertices, dtype=np.float64)
            hull_e = np.ascontiguousarray(hull.edges_unique, dtype=np.int32)
        except Exception:  # flat or degenerate point sets: qhull refuses them
            # Every vertex and every mesh edge still bound the mesh and its gel cut.
            hull_v = v
            hull_e = np.ascontiguousarray(tm.edges_unique, dtype=np.int32)
        closed = bool(tm.is_watertight and tm.is_winding_consistent and tm.volume > 0.0)
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        planes = np.ascontiguousarray(np.concatenate([n, np.einsum("ij,ij->i", n, tri[:, 0])[:, None]], axis=1))
        return RenderMesh(
            vertices=v, faces=f, hull_vertices=hull_v, hull_edges=hull_e, closed=closed, face_planes=planes
        )

    @staticmethod
    def from_trimesh(mesh: trimesh.Trimesh, name: str = "mesh") -> "RenderMesh":
        """Validate a :class:`trimesh.Trimesh` whose vertices are in metres."""
        return RenderMesh.from_arrays(mesh.vertices, mesh.faces, name=name)
