"""Exact point-to-surface distances of a triangle mesh, for checks on few points (symmetry
detection, simplification error): brute force over the triangles in numba, stopping early."""

from __future__ import annotations

import numba
import numpy as np

from .sdf import dist2_point_triangle


@numba.njit(cache=True)
def _first_outside(V, F, P, tol2):
    """Index of the first point of P (n, 3) farther than sqrt(tol2) from every triangle, or -1."""
    for i in range(P.shape[0]):
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        inside = False
        for t in range(F.shape[0]):
            a, b, c = F[t, 0], F[t, 1], F[t, 2]
            d2 = dist2_point_triangle(px, py, pz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2],
                                       V[c, 0], V[c, 1], V[c, 2])
            if d2 <= tol2:
                inside = True
                break
        if not inside:
            return i
    return -1


@numba.njit(cache=True)
def _distances(V, F, P):
    out = np.empty(P.shape[0])
    for i in range(P.shape[0]):
        best = np.inf
        for t in range(F.shape[0]):
            a, b, c = F[t, 0], F[t, 1], F[t, 2]
            d2 = dist2_point_triangle(P[i, 0], P[i, 1], P[i, 2], V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1],
                                       V[b, 2], V[c, 0], V[c, 1], V[c, 2])
            if d2 < best:
                best = d2
        out[i] = np.sqrt(best)
    return out


def all_within(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol_m: float) -> bool:
    """True when every point (n, 3) [m] lies within ``tol_m`` of the surface (vertices (v, 3),
    faces (f, 3)); stops at the first point that does not."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return bool(_first_outside(V, F, P, float(tol_m) ** 2) < 0)


def distances(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact distance (n,) [m] from each point (n, 3) to the surface; O(n * faces)."""
    V = np.ascontiguousarray(vertices, dtype=np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    return _distances(V, F, np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3))
