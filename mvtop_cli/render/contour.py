"""The object's projected outline, sampled at sub-pixel positions, scored against image gradients.

The silhouette IoU of eq. 2 sees a pose only through whole pixels of a mask, about 0.5 mm at
0.3 m. The outline itself is known to a fraction of a pixel: it is the projection of the
mesh's contour edges (between a face turned to the camera and one turned away), and where the
image has an edge there the outline of the true pose runs along it. Creases (edges whose faces
meet at more than a crease angle, both faces seen) are visible edges too and are read with
them: on a small part a lit face beside a dark one is a crease a pixel or two inside the
outline, and left unmodelled it pulls the outline onto itself. ``contour_gradient`` samples
these edges of every pose every ``spacing_px`` ROI pixels and sums the image gradient across
the edge there (the directional derivative along the projected edge's normal, bilinearly
interpolated, summed over channels), with the count of samples. It reads only the image: no
mask and no belief enters the score, so a wrong pose cannot raise its own score.

Samples hidden behind an occluder (fingers, receptacle: the renderer's inverse-depth map of
them), samples within a margin across the contour of an occluder's outline, in front of the
part or behind it (a finger's edge against the table: they would read that outline, a strong
edge that does not move with the part), and samples outside the window are skipped. Edges of
a non-convex part hidden behind the part itself would read the part's own surface; the edges
used are therefore those with both ends on the surface of the mesh's convex hull (all of a
convex part's; a connector's outer shell without the floors of its slots and cavities, whose
contour edges are mostly hidden). On a conn2 benchmark scene (seed 3000, frame 28) that raised
the mean gradient at the true pose from 9-11 to 17-25 and moved the translation peaks to within
0.4 mm of the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numba import njit, prange

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render.mesh import RenderMesh
from mvtop_cli.render.raster import chunk_count  # (imports the numba threading policy first)
from mvtop_cli.render.roi import Roi


@dataclass(frozen=True)
class ContourTopology:
    """Edge adjacency of a mesh, for finding its contour edges at any pose.

    edges : (E, 2) int32, vertex indices of every edge used (both ends on the convex hull)
    edge_faces : (E, 2) int32, the two faces sharing the edge (-1 where only one does)
    opposite : (E, 2) int32, per adjacent face the vertex not on the edge (-1 as above)
    crease : (E,) bool, the edge's faces meet at more than the crease angle (a visible edge
        inside the outline where both face the camera)
    """

    # a vertex within this fraction of the mesh's diagonal inside its hull is on the hull
    HULL_TOLERANCE = 1e-5

    edges: np.ndarray
    edge_faces: np.ndarray
    opposite: np.ndarray
    crease: np.ndarray

    @staticmethod
    def from_mesh(mesh: RenderMesh, crease_deg: float = 30.0) -> ContourTopology:
        """The topology of ``mesh``'s faces, kept for the edges with both ends on its convex
        hull, creases where the faces' normals differ by more than ``crease_deg`` [deg]; an
        edge shared by more than two faces keeps the first two (a non-manifold edge then
        counts as a contour edge at some poses)."""
        f = np.asarray(mesh.faces, dtype=np.int64)
        half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # (3F, 2) in face order
        third = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
        face = np.tile(np.arange(len(f)), 3)
        key = np.sort(half, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        order = np.argsort(inv, kind="stable")
        edge_faces = np.full((len(uniq), 2), -1, dtype=np.int32)
        opposite = np.full((len(uniq), 2), -1, dtype=np.int32)
        slot = np.zeros(len(uniq), dtype=np.int64)
        for h in order:
            e = inv[h]
            if slot[e] < 2:
                edge_faces[e, slot[e]] = face[h]
                opposite[e, slot[e]] = third[h]
                slot[e] += 1
        normals = mesh.face_planes[:, :3]
        n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        both = edge_faces[:, 1] >= 0
        cos = np.where(both, np.einsum("ij,ij->i", n[edge_faces[:, 0]], n[np.maximum(edge_faces[:, 1], 0)]), 1.0)
        crease = both & (cos < np.cos(np.radians(crease_deg)))
        keep = ContourTopology._on_hull(mesh.vertices, mesh.faces)
        keep = keep[uniq[:, 0]] & keep[uniq[:, 1]]
        return ContourTopology(np.ascontiguousarray(uniq[keep], dtype=np.int32),
                               np.ascontiguousarray(edge_faces[keep]), np.ascontiguousarray(opposite[keep]),
                               np.ascontiguousarray(crease[keep]))

    @staticmethod
    def _on_hull(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(V,) bool: the vertices on the surface of the mesh's convex hull (all of them for a
        flat mesh, which has no hull volume)."""
        v = np.asarray(vertices, dtype=np.float64)
        try:
            hull = trimesh.Trimesh(v, np.asarray(faces), process=False).convex_hull
        except Exception:  # flat or degenerate point sets: qhull refuses them
            return np.ones(len(v), dtype=bool)
        n = hull.face_normals
        d = np.einsum("ij,ij->i", n, hull.vertices[hull.faces[:, 0]])
        tol = ContourTopology.HULL_TOLERANCE * float(np.linalg.norm(np.ptp(v, axis=0)))
        return (v @ n.T - d).max(axis=1) >= -tol


@njit(cache=True, inline="always")
def _bilinear(img, x, y):
    """``img`` (h, w) at the sub-pixel position (x, y) (pixel centres at integers); the caller
    keeps (x, y) inside [0, w - 1] x [0, h - 1]."""
    h, w = img.shape
    x0 = min(int(x), w - 2) if w > 1 else 0
    y0 = min(int(y), h - 2) if h > 1 else 0
    fx = x - x0
    fy = y - y0
    x1 = min(x0 + 1, w - 1)
    y1 = min(y0 + 1, h - 1)
    top = img[y0, x0] * (1.0 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1.0 - fx) + img[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


@njit(cache=True)
def _contour_pose(T, verts, planes, edges, edge_faces, opposite, crease, intr, width, height, znear, thr, use_thr,
                  margin, depth_step, gx, gy, spacing, cam, front):
    """(sum of |gradient . normal| over the visible samples, their count) for one pose."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    nv = verts.shape[0]
    for i in range(nv):
        for r in range(3):
            cam[i, r] = T[r, 0] * verts[i, 0] + T[r, 1] * verts[i, 1] + T[r, 2] * verts[i, 2] + T[r, 3]
    # the camera centre in the mesh frame: c = -R^T t
    c0 = -(T[0, 0] * T[0, 3] + T[1, 0] * T[1, 3] + T[2, 0] * T[2, 3])
    c1 = -(T[0, 1] * T[0, 3] + T[1, 1] * T[1, 3] + T[2, 1] * T[2, 3])
    c2 = -(T[0, 2] * T[0, 3] + T[1, 2] * T[1, 3] + T[2, 2] * T[2, 3])
    for f in range(planes.shape[0]):
        front[f] = planes[f, 0] * c0 + planes[f, 1] * c1 + planes[f, 2] * c2 > planes[f, 3]
    total = 0.0
    count = 0
    nch = gx.shape[0]
    for e in range(edges.shape[0]):
        f0 = edge_faces[e, 0]
        f1 = edge_faces[e, 1]
        if f1 < 0:
            if not front[f0]:
                continue
            k = 0
        elif front[f0] != front[f1]:
            k = 0 if front[f0] else 1
        elif front[f0] and crease[e]:
            k = 0
        else:
            continue
        a = edges[e, 0]
        b = edges[e, 1]
        o = opposite[e, k]
        za, zb, zo = cam[a, 2], cam[b, 2], cam[o, 2]
        if za <= znear or zb <= znear or zo <= znear:
            continue
        ua, va = fx * cam[a, 0] / za + cx, fy * cam[a, 1] / za + cy
        ub, vb = fx * cam[b, 0] / zb + cx, fy * cam[b, 1] / zb + cy
        uo, vo = fx * cam[o, 0] / zo + cx, fy * cam[o, 1] / zo + cy
        du, dv = ub - ua, vb - va
        length = np.sqrt(du * du + dv * dv)
        if length < 1e-9:
            continue
        # unit normal of the projected edge, pointing away from the front face (outwards)
        nx, ny = dv / length, -du / length
        if (uo - ua) * nx + (vo - va) * ny > 0.0:
            nx, ny = -nx, -ny
        m = max(1, int(length / spacing + 0.5))
        iza, izb = 1.0 / za, 1.0 / zb
        for s in range(m):
            t = (s + 0.5) / m
            x = ua + t * du
            y = va + t * dv
            if x < 0.0 or y < 0.0 or x > width - 1 or y > height - 1:
                continue
            if use_thr:
                # hidden, or within ``margin`` across the contour of an occluder's outline, in
                # front of the part or behind it (the sample would read that outline's edge)
                iz = iza + t * (izb - iza)  # inverse depth is linear along the projected edge
                here = thr[int(y + 0.5) * width + int(x + 0.5)]
                if iz <= here:
                    continue
                near = False
                for side in (-1.0, 1.0):
                    for r in range(1, int(margin) + 1):
                        px = min(max(x + side * r * nx, 0.0), width - 1.0)
                        py = min(max(y + side * r * ny, 0.0), height - 1.0)
                        there = thr[int(py + 0.5) * width + int(px + 0.5)]
                        # an outline: an occluder on one side only, or one occluder before another
                        # (a pixel occluder's inf hides everything: its edge is an outline too)
                        if there != here and (max(there, here) == np.inf
                                              or abs(there - here) > depth_step * max(there, here)):
                            near = True
                if near:
                    continue
            g = 0.0
            for ch in range(nch):
                g += abs(_bilinear(gx[ch], x, y) * nx + _bilinear(gy[ch], x, y) * ny)
            total += g
            count += 1
    return total, count


@njit(cache=True, parallel=True)
def contour_gradient_kernel(poses, verts, planes, edges, edge_faces, opposite, crease, intr, width, height, znear,
                            thr, use_thr, margin, depth_step, gx, gy, spacing, nchunks, out_sum, out_count):
    """Per pose of ``poses`` (N, 4, 4): the summed gradient across the visible contour and
    the number of samples, into ``out_sum`` (N,) float64 and ``out_count`` (N,) int64."""
    n = poses.shape[0]
    for c in prange(nchunks):
        cam = np.empty((verts.shape[0], 3))
        front = np.empty(planes.shape[0], dtype=np.bool_)
        for i in range(c * n // nchunks, (c + 1) * n // nchunks):
            s, k = _contour_pose(poses[i], verts, planes, edges, edge_faces, opposite, crease, intr, width, height,
                                 znear, thr, use_thr, margin, depth_step, gx, gy, spacing, cam, front)
            out_sum[i] = s
            out_count[i] = k


def contour_gradient(mesh: RenderMesh, topology: ContourTopology, T_sensor_object: np.ndarray,
                     camera: PinholeCamera, roi: Roi, gx: np.ndarray, gy: np.ndarray,
                     occluder_inverse_depth: np.ndarray | None, spacing_px: float, margin_px: float,
                     depth_step: float, znear_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The image gradient across the visible projected contour of ``mesh`` at every pose.

    T_sensor_object : (N, 4, 4) poses of the mesh in the camera's optical frame [m]
    camera, roi : the camera and the window ``gx``/``gy`` cover (ROI pixels)
    gx, gy : (C, h, w) float32, per channel the image derivative along ROI columns / rows
        [image units per ROI pixel]
    occluder_inverse_depth : (h * w,) inverse depth [1/m] a contour point must exceed to be
        seen, or None without occluders
    spacing_px : distance between contour samples [ROI pixels]
    margin_px : a sample this close across the contour to an occluder's outline is skipped
        too [ROI pixels]: it would read that outline's edge
    depth_step : an outline is where the occluders' inverse depth changes by more than this
        fraction between neighbouring samples (an occluder's edge, or one occluder in front of
        another, e.g. a finger before the table)
    Returns (sum (N,) float64 over the visible samples of |gradient . contour normal| summed
    over channels [image units per pixel]; count (N,) int64 of visible samples).
    """
    T = np.ascontiguousarray(np.asarray(T_sensor_object, dtype=np.float64).reshape(-1, 4, 4))
    rows, cols = roi.shape
    gx = np.ascontiguousarray(gx, dtype=np.float32)
    gy = np.ascontiguousarray(gy, dtype=np.float32)
    if gx.shape != gy.shape or gx.ndim != 3 or gx.shape[1:] != (rows, cols):
        raise ValueError(f"gradients {gx.shape} / {gy.shape} must be (C, {rows}, {cols}), the ROI's size")
    if not spacing_px > 0 or not margin_px >= 0:
        raise ValueError(f"spacing_px must be > 0 and margin_px >= 0, got {spacing_px}, {margin_px}")
    cam = roi.camera(camera)
    intr = np.array([cam.fx, cam.fy, cam.cx, cam.cy], dtype=np.float64)
    use_thr = occluder_inverse_depth is not None
    thr = np.asarray(occluder_inverse_depth, dtype=np.float64) if use_thr else np.zeros(1)
    if use_thr and thr.shape != (rows * cols,):
        raise ValueError(f"occluder_inverse_depth {thr.shape} must be ({rows * cols},)")
    total = np.zeros(len(T))
    count = np.zeros(len(T), dtype=np.int64)
    contour_gradient_kernel(T, mesh.vertices, mesh.face_planes, topology.edges, topology.edge_faces,
                            topology.opposite, topology.crease, intr, cols, rows, float(znear_m), thr, use_thr,
                            float(margin_px), float(depth_step), gx, gy, float(spacing_px), chunk_count(len(T)),
                            total, count)
    return total, count
