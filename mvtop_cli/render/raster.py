"""Numba z-buffer rasteriser: many poses of one triangle mesh into small images, in parallel.

Conventions match OpenGL with the intrinsics of :meth:`Roi.camera`: pixel ``(r, c)`` is
sampled at its centre ``(u, v) = (c, r)``; inverse depth ``1/z`` is interpolated linearly in
screen space (perspective-correct); triangles are clipped at the near plane ``z = znear``.

A *threshold map* ``thr`` (h * w,) of inverse depths lets a fragment count only where it is
nearer than something: ``0`` everywhere for a plain silhouette, the occluders' inverse depth
for occlusion, ``1 / gel_distance`` for a tactile contact mask. Because a pixel's nearest
surface passes such a test exactly when some surface at that pixel does, masks need no
z-buffer: a pixel is set by the first passing fragment and later fragments skip it.

Triangles are filled row by row between the crossings of their edges. Edge lines are
computed from their endpoints in a canonical order (lexicographic in ``(u, v)``), so the two
triangles sharing an edge compute a bit-identical crossing ``t`` on every row; one fills up
to ``floor(t)``, the other from ``ceil(t)``, and no pixel centre between them is missed. This
relies on exact IEEE arithmetic, hence no ``fastmath`` here.

Scoring without keeping the masks has two kernels that set and count exactly the same pixels.
``score_masks_kernel`` sets a byte mask and counts each pixel as it is set. ``score_runs_kernel``,
for a threshold that is one value over the window (none, or a tactile gel plane without
occluders), sets each row's span of a triangle in a bit-packed mask (64 pixels a word) with
whole-word stores and counts by popcount at the end. The pixels passing a constant threshold
form one run at either end of a span, because the interpolated inverse depth is monotone along
a row in floating point too (a rounded product and sum of monotone terms); the run's end is
found by bisection with the same expression a pixel is tested with. Spans shorter than 16
pixels are tested pixel by pixel, which is cheaper than bounding them. Runs pay where a
triangle covers many pixels (measured on the sample logs' tactile masks: 2x faster for the
cube, 1.5x for the shaft peg, 1.1x for the plug) and lose on fine meshes and small windows
(the connectors: 13-19 % slower), so the renderer picks per call (``NumbaMaskRenderer``).

Both kernels can also take a per-pixel *limit* (an inverse depth at least the threshold, e.g.
a tactile pad's measured indentation): the observed pixels that some fragment comes nearer than
the limit are taken back from the area and the intersection, once each, in the same pass.
Such a pixel is always in the mask (the fragment passes the threshold too). The test is per
observed pixel of each row a triangle spans, skipped where the row's largest inverse depth (at
one end, by the same monotonicity) does not exceed the least limit (``limit_blocks``: per
block of ``LIMIT_BLOCK`` columns): the byte kernel tests each pixel as it sets it, computing
its inverse depth once (``_row_may_pass`` per row); the runs kernel, which sets no pixel one
by one, in a pass of its own per row and block (``_over_limit``).

Cost per pose: a transform per vertex, a plane test per face (back faces of closed meshes are
culled) and roughly 50 ns per front face plus 1-3 ns per covered pixel (with runs: a few word
stores per row of a triangle) on this machine, so meshes of a few thousand faces keep to tens
of microseconds.
"""

from __future__ import annotations

import math

import numpy as np
from numba import get_num_threads, njit, prange

from mvtop_cli import _threads  # noqa: F401  (sets OMP_WAIT_POLICY before any kernel runs)
from mvtop_cli.bitmasks import popcount

# Rows of the per-vertex scratch array ``scr``: u, v, 1/z, 1 if z >= znear.
_U, _V, _IZ, _OK = 0, 1, 2, 3

# What a fragment does (``mode``): set a byte mask, keep the largest inverse depth, set a
# bit-packed mask (``bits``, ``nw`` uint64 words a row; the threshold must be constant), or
# either mask and also find the observed pixels some fragment comes nearer than a limit.
MODE_MASK, MODE_ZBUF, MODE_BITS, MODE_LIMIT, MODE_BITS_LIMIT = 0, 1, 2, 3, 4
# A byte-mask pixel found nearer than the limit (set pixels are 1).
_OVER = 2
# Columns per block of ``limit_blocks``.
LIMIT_BLOCK = 16
# Spans shorter than this [pixels] are set pixel by pixel in MODE_BITS.
_SHORT_RUN = 16
_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(cache=True, inline="always")
def _set_run(bits, row, a, b):
    """Set bits ``a .. b`` (columns, inclusive) of the bit-packed row starting at word ``row``."""
    wa = row + (a >> 6)
    wb = row + (b >> 6)
    lo = _ALL << np.uint64(a & 63)
    hi = _ALL >> np.uint64(63 - (b & 63))
    if wa == wb:
        bits[wa] |= lo & hi
        return
    bits[wa] |= lo
    for k in range(wa + 1, wb):
        bits[k] = _ALL
    bits[wb] |= hi


@njit(cache=True, inline="always")
def _set_passing_run(bits, row, a, b, izy, P, u0, t):
    """Set the pixels ``a .. b`` of one row whose inverse depth ``izy + P (x - u0)`` is not
    ``<= t`` (the per-pixel test of ``_raster_triangle``). The values are monotone in ``x``,
    so the passing pixels are a run at one end of ``a .. b``, its end found by bisection."""
    pa = not (izy + P * (a - u0) <= t)
    pb = not (izy + P * (b - u0) <= t)
    if pa == pb:
        if pa:
            _set_run(bits, row, a, b)
        return
    # The test flips once in a .. b: bisect for the last pixel that agrees with a.
    lo, hi = a, b
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if (not (izy + P * (mid - u0) <= t)) == pa:
            lo = mid
        else:
            hi = mid
    if pa:
        _set_run(bits, row, a, lo)
    else:
        _set_run(bits, row, hi, b)


@njit(cache=True, inline="always")
def _edge(pu, pv, qu, qv, orient):
    """Line a x + b y + c = 0 through two projected points, from the points in canonical
    order, and the side s (+1/-1) on which the triangle (orientation ``orient``) lies.
    Returns (1 / a, b, c, s a), or (0, b, c, s) for a horizontal edge."""
    s = orient
    if qu < pu or (qu == pu and qv < pv):
        pu, pv, qu, qv = qu, qv, pu, pv
        s = -s
    a = pv - qv
    if a == 0.0:
        return 0.0, qu - pu, pu * qv - qu * pv, s
    # 1 / a once per edge rather than a division per row.
    return 1.0 / a, qu - pu, pu * qv - qu * pv, s * a


@njit(cache=True, inline="always")
def _span(inv_a, b, c, sa, y, lo, hi):
    """Narrow the pixel-centre span [lo, hi] of row ``y`` to s (a x + b y + c) >= 0, given
    ``inv_a = 1 / a`` (0 for a == 0) and ``sa = s a`` (for a == 0, the sign s)."""
    q = b * y + c
    if inv_a == 0.0:
        if sa * q < 0.0:
            return 1.0, 0.0
        return lo, hi
    t = -q * inv_a
    if sa > 0.0:
        return max(lo, np.ceil(t)), hi
    return lo, min(hi, np.floor(t))


@njit(cache=True)
def _over_limit(mask, obs, lim, lmin, yi, base, a, b, izy, P, u0, bisect):
    """Mark (``mask`` ``_OVER``) and count the observed pixels ``a .. b`` of row ``yi`` (index
    ``base + x``), not marked before, whose inverse depth ``izy + P (x - u0)`` is not ``<= lim``.
    A block of ``LIMIT_BLOCK`` columns is skipped when the row's largest inverse depth in it (at
    one end: the values are monotone, given ``bisect``) is at most ``lmin``, the block's least
    limit over its observed pixels (``limit_blocks``)."""
    n = 0
    k = a // LIMIT_BLOCK
    while k * LIMIT_BLOCK <= b:
        xa = max(a, k * LIMIT_BLOCK)
        xb = min(b, k * LIMIT_BLOCK + LIMIT_BLOCK - 1)
        lo_block = lmin[yi, k]
        k += 1
        if bisect and max(izy + P * (xa - u0), izy + P * (xb - u0)) <= lo_block:
            continue
        for xi in range(xa, xb + 1):
            idx = base + xi
            if obs[idx] and mask[idx] != _OVER and not izy + P * (xi - u0) <= lim[idx]:
                mask[idx] = _OVER
                n += 1
    return n


@njit(cache=True, inline="always")
def _row_may_pass(lmin, yi, a, b, izy, P, u0):
    """Whether a fragment of row ``yi``, columns ``a .. b``, with the inverse depth ``izy + P (x -
    u0)`` (monotone in ``x``: its largest at one end) may pass the least limit ``lmin`` of the
    blocks it spans (``limit_blocks``)."""
    top = max(izy + P * (a - u0), izy + P * (b - u0))
    for k in range(a // LIMIT_BLOCK, b // LIMIT_BLOCK + 1):
        if not top <= lmin[yi, k]:
            return True
    return False


def limit_blocks(lim: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """The least of the limit ``lim`` (h, w) over the observed pixels ``obs`` (h, w) of each block
    of ``LIMIT_BLOCK`` columns of a row: (h, ceil(w / LIMIT_BLOCK)) float64, ``inf`` for a block
    with none."""
    h, w = obs.shape
    nb = -(-w // LIMIT_BLOCK)
    padded = np.full((h, nb * LIMIT_BLOCK), np.inf)
    padded[:, :w] = np.where(obs, lim, np.inf)
    return padded.reshape(h, nb, LIMIT_BLOCK).min(axis=2)


@njit(cache=True, inline="always")
def _raster_triangle(
    u0, v0, iz0, u1, v1, iz1, u2, v2, iz2,
    width, height, thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin,
):  # fmt: skip
    """Fill one projected triangle. ``MODE_MASK`` sets unset pixels whose fragment passes
    ``thr`` and returns (new pixels, new pixels where ``obs``); ``MODE_ZBUF`` keeps the largest
    inverse depth per pixel in ``zbuf``; ``MODE_BITS`` sets the passing pixels in ``bits``
    (row ``y`` at word ``y * nw``) for a threshold equal to ``thr_min`` everywhere. The last
    two return (0, 0). ``MODE_LIMIT`` is ``MODE_MASK`` (``mask`` uint8) with ``zbuf`` a second
    per-pixel inverse depth, at least ``thr``: an observed pixel (``obs`` 0 or 1) that a fragment
    comes nearer than it is taken back from both counts, once, tested as the pixel is set (``lmin``
    the ``limit_blocks`` of ``zbuf`` and ``obs``). ``MODE_BITS_LIMIT`` is ``MODE_BITS`` returning
    that take-back, (-n, -n), with ``mask`` (uint8) marking those pixels."""
    if use_thr and max(iz0, max(iz1, iz2)) <= thr_min:
        return 0, 0
    # Pixel-centre bounding box, clipped to the image.
    xa = max(np.ceil(min(u0, min(u1, u2))), 0.0)
    xb = min(np.floor(max(u0, max(u1, u2))), width - 1.0)
    ya = max(np.ceil(min(v0, min(v1, v2))), 0.0)
    yb = min(np.floor(max(v0, max(v1, v2))), height - 1.0)
    if xa > xb or ya > yb:
        return 0, 0
    area2 = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    if area2 == 0.0 or not math.isfinite(area2):
        return 0, 0
    orient = 1.0 if area2 > 0.0 else -1.0
    # Inverse-depth plane iz = iz0 + P (x - u0) + Q (y - v0), needed only for depth tests.
    P = 0.0
    Q = 0.0
    zmode = mode == MODE_ZBUF
    limit = mode == MODE_LIMIT or mode == MODE_BITS_LIMIT
    if use_thr or zmode or limit:
        P = ((iz1 - iz0) * (v2 - v0) - (iz2 - iz0) * (v1 - v0)) / area2
        Q = ((u1 - u0) * (iz2 - iz0) - (u2 - u0) * (iz1 - iz0)) / area2
    # Bisection relies on finite, monotone rows (P from a near-degenerate triangle may not be).
    bisect = math.isfinite(P) and math.isfinite(Q)
    a0, b0, c0, s0 = _edge(u0, v0, u1, v1, orient)
    a1, b1, c1, s1 = _edge(u1, v1, u2, v2, orient)
    a2, b2, c2, s2 = _edge(u2, v2, u0, v0, orient)
    area = 0
    inter = 0
    iw = int(width)
    for yi in range(int(ya), int(yb) + 1):
        y = float(yi)
        lo, hi = _span(a0, b0, c0, s0, y, xa, xb)
        lo, hi = _span(a1, b1, c1, s1, y, lo, hi)
        lo, hi = _span(a2, b2, c2, s2, y, lo, hi)
        if not lo <= hi:  # also skips NaN spans
            continue
        base = yi * iw
        izy = iz0 + Q * (y - v0)
        if mode == MODE_BITS or mode == MODE_BITS_LIMIT:
            ilo, ihi = int(lo), int(hi)
            row = yi * nw
            if not use_thr:
                _set_run(bits, row, ilo, ihi)
            elif bisect and ihi - ilo >= _SHORT_RUN:
                _set_passing_run(bits, row, ilo, ihi, izy, P, u0, thr_min)
            else:  # a short span, or a depth plane that is not finite: pixel by pixel
                word = ilo >> 6
                acc = np.uint64(0)
                for xi in range(ilo, ihi + 1):
                    if xi >> 6 != word:
                        bits[row + word] |= acc
                        acc = np.uint64(0)
                        word = xi >> 6
                    if not (izy + P * (xi - u0) <= thr_min):
                        acc |= np.uint64(1) << np.uint64(xi & 63)
                bits[row + word] |= acc
        elif mode == MODE_LIMIT:
            # The byte mask and the limit in one pass: the pixel's inverse depth is computed once.
            # The limit is tested only in rows where a fragment may come nearer than some observed pixel's.
            ilo, ihi = int(lo), int(hi)
            test = not bisect or _row_may_pass(lmin, yi, ilo, ihi, izy, P, u0)
            for xi in range(ilo, ihi + 1):
                idx = base + xi
                iz = izy + P * (xi - u0)
                m = mask[idx]
                if m == 0:
                    if use_thr and iz <= thr[idx]:
                        continue  # nor can it pass the limit, which is at least the threshold
                    mask[idx] = 1
                    area += 1
                    inter += obs[idx]
                    m = 1
                if test and m != _OVER and obs[idx] and not iz <= zbuf[idx]:
                    mask[idx] = _OVER
                    area -= 1
                    inter -= 1
        else:
            for xi in range(int(lo), int(hi) + 1):
                idx = base + xi
                if zmode:
                    iz = izy + P * (xi - u0)
                    if iz > zbuf[idx] and (not use_thr or iz > thr[idx]):
                        zbuf[idx] = iz
                elif not mask[idx]:
                    if use_thr:
                        iz = izy + P * (xi - u0)
                        if iz <= thr[idx]:
                            continue
                    mask[idx] = True
                    area += 1
                    inter += obs[idx]
        if mode == MODE_BITS_LIMIT:
            over = _over_limit(mask, obs, zbuf, lmin, yi, base, int(lo), int(hi), izy, P, u0, bisect)
            area -= over
            inter -= over
    return area, inter


@njit(cache=True)
def _raster_pose(
    T, verts, faces, planes, cull, intr, width, height, znear,
    thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin, cam, scr,
):  # fmt: skip
    """Rasterise the mesh (verts (V, 3) [m], faces (F, 3)) at pose ``T`` (4, 4) in the
    camera's optical frame, with ``intr`` = (fx, fy, cx, cy). With ``cull`` (a closed
    mesh), faces whose plane ``planes[f] = (n, n . v0)`` (outward normal n) does not face
    the camera are skipped, unless the near plane cuts the mesh. ``cam`` (V, 3) and ``scr``
    (V, 4) are scratch. Returns (area, intersection) in mask mode."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    n_near = 0
    for i in range(verts.shape[0]):
        x, y, z = verts[i, 0], verts[i, 1], verts[i, 2]
        px = r00 * x + r01 * y + r02 * z + t0
        py = r10 * x + r11 * y + r12 * z + t1
        pz = r20 * x + r21 * y + r22 * z + t2
        cam[i, 0] = px
        cam[i, 1] = py
        cam[i, 2] = pz
        if pz >= znear:
            iz = 1.0 / pz
            scr[i, _U] = fx * px * iz + cx
            scr[i, _V] = fy * py * iz + cy
            scr[i, _IZ] = iz
            scr[i, _OK] = 1.0
        else:
            scr[i, _OK] = 0.0
            n_near += 1
    # A closed mesh wholly beyond the near plane shows only front faces. Otherwise the
    # camera may be inside it, or the near plane may cut it open: draw every face.
    cull = cull and n_near == 0
    # Camera centre in the mesh frame, -R^T t: a face is front-facing when n . c > n . v0.
    ox = -(r00 * t0 + r10 * t1 + r20 * t2)
    oy = -(r01 * t0 + r11 * t1 + r21 * t2)
    oz = -(r02 * t0 + r12 * t1 + r22 * t2)
    area = 0
    inter = 0
    for f in range(faces.shape[0]):
        if cull and planes[f, 0] * ox + planes[f, 1] * oy + planes[f, 2] * oz <= planes[f, 3]:
            continue  # back-facing or edge-on
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        n_ok = scr[i0, _OK] + scr[i1, _OK] + scr[i2, _OK]
        if n_ok == 3.0:
            a, b = _raster_triangle(
                scr[i0, _U], scr[i0, _V], scr[i0, _IZ],
                scr[i1, _U], scr[i1, _V], scr[i1, _IZ],
                scr[i2, _U], scr[i2, _V], scr[i2, _IZ],
                width, height, thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin,
            )  # fmt: skip
            area += a
            inter += b
        elif n_ok > 0.0:
            a, b = _raster_clipped(
                cam, i0, i1, i2, fx, fy, cx, cy, width, height, znear,
                thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin,
            )  # fmt: skip
            area += a
            inter += b
    return area, inter


@njit(cache=True)
def _raster_clipped(
    cam, i0, i1, i2, fx, fy, cx, cy, width, height, znear,
    thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin,
):  # fmt: skip
    """Rasterise triangle (i0, i1, i2) of camera-frame vertices ``cam`` (V, 3) after clipping
    it at z = znear (Sutherland-Hodgman against one plane; at most a quad, drawn as a fan)."""
    pu = np.empty(4)
    pv = np.empty(4)
    piz = np.empty(4)
    m = 0
    idx = (i0, i1, i2)
    for k in range(3):
        ia = idx[k]
        ib = idx[(k + 1) % 3]
        za = cam[ia, 2]
        zb = cam[ib, 2]
        if za >= znear:
            piz[m] = 1.0 / za
            pu[m] = fx * cam[ia, 0] * piz[m] + cx
            pv[m] = fy * cam[ia, 1] * piz[m] + cy
            m += 1
        if (za >= znear) != (zb >= znear):
            t = (znear - za) / (zb - za)
            piz[m] = 1.0 / znear
            pu[m] = fx * (cam[ia, 0] + t * (cam[ib, 0] - cam[ia, 0])) * piz[m] + cx
            pv[m] = fy * (cam[ia, 1] + t * (cam[ib, 1] - cam[ia, 1])) * piz[m] + cy
            m += 1
    area = 0
    inter = 0
    for k in range(1, m - 1):
        a, b = _raster_triangle(
            pu[0], pv[0], piz[0], pu[k], pv[k], piz[k], pu[k + 1], pv[k + 1], piz[k + 1],
            width, height, thr, thr_min, use_thr, mode, mask, zbuf, obs, bits, nw, lmin,
        )  # fmt: skip
        area += a
        inter += b
    return area, inter


def chunk_count(n: int) -> int:
    """Parallel chunks for ``n`` poses."""
    # A few chunks per thread balance the load; each chunk allocates its scratch once.
    return max(1, min(n, 8 * get_num_threads()))


@njit(cache=True, parallel=True)
def render_masks_kernel(
    poses, verts, faces, planes, cull, intr, width, height, znear, thr, thr_min, use_thr, nchunks, out
):
    """Masks of ``poses`` (N, 4, 4) into ``out`` (N, h * w) bool (cleared by the caller)."""
    n = poses.shape[0]
    nv = verts.shape[0]
    zdummy = np.zeros(1, dtype=np.float32)
    odummy = np.zeros(width * height, dtype=np.uint8)
    bdummy = np.zeros(1, dtype=np.uint64)
    ldummy = np.zeros((1, 1))
    for c in prange(nchunks):
        cam = np.empty((nv, 3))
        scr = np.empty((nv, 4))
        for i in range(c * n // nchunks, (c + 1) * n // nchunks):
            _raster_pose(
                poses[i], verts, faces, planes, cull, intr, width, height, znear,
                thr, thr_min, use_thr, MODE_MASK, out[i], zdummy, odummy, bdummy, 0, ldummy, cam, scr,
            )  # fmt: skip


def pack_rows(mask: np.ndarray) -> np.ndarray:
    """Bit-packed copy (h * nw,) uint64 of ``mask`` (h, w) bool: column ``c`` of row ``r`` is
    bit ``c % 64`` of word ``r * nw + c // 64``, ``nw = ceil(w / 64)``."""
    h, w = mask.shape
    nw = (w + 63) // 64
    padded = np.zeros((h, nw * 64), dtype=bool)
    padded[:, :w] = mask
    return np.packbits(padded, axis=1, bitorder="little").view("<u8").astype(np.uint64).reshape(-1)


@njit(cache=True, parallel=True)
def score_masks_kernel(
    poses, verts, faces, planes, cull, intr, width, height, znear, thr, thr_min, use_thr, lim, lmin, use_lim, nchunks,
    obs, area, inter,
):  # fmt: skip
    """Rendered area and intersection with ``obs`` (h * w,) uint8 per pose, without keeping
    the masks: (N,) int64 each. With ``use_lim`` (``obs`` 0 or 1), the observed pixels where a
    fragment's inverse depth exceeds ``lim`` (h * w,) (at least ``thr``) are left out of both;
    ``lmin`` its ``limit_blocks``."""
    n = poses.shape[0]
    nv = verts.shape[0]
    bdummy = np.zeros(1, dtype=np.uint64)
    mode = MODE_LIMIT if use_lim else MODE_MASK
    for c in prange(nchunks):
        cam = np.empty((nv, 3))
        scr = np.empty((nv, 4))
        mask = np.empty(width * height, dtype=np.uint8)
        for i in range(c * n // nchunks, (c + 1) * n // nchunks):
            mask[:] = 0
            a, b = _raster_pose(
                poses[i], verts, faces, planes, cull, intr, width, height, znear,
                thr, thr_min, use_thr, mode, mask, lim, obs, bdummy, 0, lmin, cam, scr,
            )  # fmt: skip
            area[i] = a
            inter[i] = b


@njit(cache=True, parallel=True)
def score_runs_kernel(
    poses, verts, faces, planes, cull, intr, width, height, znear, thr_min, use_thr, lim, lmin, use_lim, nchunks,
    obs_bits, obs, area, inter,
):  # fmt: skip
    """``score_masks_kernel`` for a threshold ``thr_min`` the same over the window (or none),
    by runs in a bit-packed mask: area and intersection with ``obs_bits`` (``pack_rows``) per
    pose, (N,) int64 each. With ``use_lim``, ``score_masks_kernel``'s limit ``lim`` and ``lmin``
    on the observed pixels ``obs`` (h * w,) uint8."""
    n = poses.shape[0]
    nv = verts.shape[0]
    nw = (width + 63) // 64
    tdummy = np.zeros(1)
    mode = MODE_BITS_LIMIT if use_lim else MODE_BITS
    for c in prange(nchunks):
        cam = np.empty((nv, 3))
        scr = np.empty((nv, 4))
        bits = np.zeros(height * nw, dtype=np.uint64)
        over = np.zeros(width * height if use_lim else 1, dtype=np.uint8)
        for i in range(c * n // nchunks, (c + 1) * n // nchunks):
            a, b = _raster_pose(
                poses[i], verts, faces, planes, cull, intr, width, height, znear,
                tdummy, thr_min, use_thr, mode, over, lim, obs, bits, nw, lmin, cam, scr,
            )  # fmt: skip
            if a < 0:  # pixels taken back by the limit: clear their marks
                over[:] = 0
            for k in range(height * nw):
                a += popcount(bits[k])
                b += popcount(bits[k] & obs_bits[k])
                bits[k] = 0
            area[i] = a
            inter[i] = b


@njit(cache=True, parallel=True)
def render_invdepth_kernel(
    poses, verts, faces, planes, cull, intr, width, height, znear, thr, thr_min, use_thr, nchunks, out
):
    """Largest inverse depth [1/m] per pixel into ``out`` (N, h * w) float32 (zeroed by the
    caller; 0 where no fragment passes ``thr``)."""
    n = poses.shape[0]
    nv = verts.shape[0]
    mdummy = np.zeros(1, dtype=np.bool_)
    odummy = np.zeros(1, dtype=np.uint8)
    bdummy = np.zeros(1, dtype=np.uint64)
    ldummy = np.zeros((1, 1))
    for c in prange(nchunks):
        cam = np.empty((nv, 3))
        scr = np.empty((nv, 4))
        for i in range(c * n // nchunks, (c + 1) * n // nchunks):
            _raster_pose(
                poses[i], verts, faces, planes, cull, intr, width, height, znear,
                thr, thr_min, use_thr, MODE_ZBUF, mdummy, out[i], odummy, bdummy, 0, ldummy, cam, scr,
            )  # fmt: skip
