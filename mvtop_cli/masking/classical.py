"""Classical camera masking backend (no model weights): colour/watershed/edge proposals, GrabCut prompts.

Zero-shot mode (:meth:`ClassicalCameraBackend.proposals`) plays the part SAM2's automatic
mask generator plays in the paper (section IV-A, Algorithm 1): it segments the search
window of an RGB image in three independent ways and pools the regions as candidates:

* k-means colour clustering in CIE Lab for several ``k``: every 4-connected component of a
  cluster, and the union of same-cluster components within ``bridge_gap_px`` of each other
  (the visible pieces of a part cut by an occluding finger);
* a watershed over-segmentation of the colour gradient, merged greedily by colour
  difference and boundary strength; the regions at a few levels of the hierarchy;
* the regions enclosed by Canny edges.

Candidates are ranked by the mean gradient along their outline over (1 + the mean gradient
inside), discounted by the share of the outline on the window border (a part stands out
and is smooth inside; background runs out of the window). The best ones are also joined
pairwise when disjoint, close and alike in median colour (pieces of a part split by an
occluder of the part's own colour), and, opt-in (``adjacent_contact_px``), when they touch
whatever their colours (the faces of one part lit differently). Holes up to
``max_hole_fraction`` of a region (a specular highlight) are filled; proposals with IoU >
``merge_iou`` are merged and at most ``max_proposals`` kept. All of it runs on the window
downsampled to ``work_max_side_px``.

Promptable mode (:meth:`ClassicalCameraBackend.prompt`), for when the pose belief has
converged, refines the CAD silhouette rendered at the current estimate with GrabCut.
"""

from __future__ import annotations

import dataclasses
import difflib
import heapq
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numba import njit

from mvtop_cli.bitmasks import mask_nms
from mvtop_cli.errors import ConfigError
from mvtop_cli.masking.base import roi_window

# GrabCut labels (cv2.GC_*), named here for readability.
_BGD, _FGD, _PR_BGD, _PR_FGD = cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD
_CROSS3 = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_SQUARE3 = np.ones((3, 3), np.uint8)


def _disk(radius_px: int) -> np.ndarray:
    """Elliptic structuring element of the given radius (a (2r+1)^2 kernel)."""
    r = max(int(radius_px), 0)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


@dataclass(frozen=True)
class ClassicalOptions:
    """Options of :class:`ClassicalCameraBackend`; pixel sizes are full-image pixels unless noted.

    Zero-shot proposals
    -------------------
    work_max_side_px : the search window is downsampled (area averaging) so that its longer
        side is at most this many pixels; it bounds the cost of a call
    bilateral_sigma_colour : colour sigma [8-bit levels] of the edge-preserving smoothing
        applied at work resolution before segmenting (removes sensor noise, keeps edges)
    cluster_counts : the ``k`` values of the k-means colour clusterings
    lightness_weight : weight of Lab L* against a*, b* in the k-means distance (below 1
        makes shading matter less than hue)
    kmeans_iterations, kmeans_sample_px : Lloyd iterations, and pixels sampled to fit centres
    seed : seed of the k-means generator (re-seeded every call)
    superpixel_spacing_work_px : watershed seed spacing, in work-resolution pixels
    hierarchy_region_counts : region counts at which the merged watershed partition is
        sampled for proposals
    merge_size_exponent : merge costs grow with the pair's size to this power (0: colour
        and edge only; 1 made a grey part under a grey finger survive longest in tests)
    canny_low, canny_high : Canny hysteresis thresholds on the smoothed lightness (8-bit)
    min_area_px : smallest proposal [px^2]
    max_area_fraction : largest proposal, as a fraction of the search window's area
    bridge_gap_px : same-colour components at most this far apart are also proposed as one
        mask (an occluding finger is narrower than this in a 640x480 view)
    max_hole_fraction : holes up to this fraction of a region's area are filled
    union_pool, union_colour_tolerance : the best ``union_pool`` regions are also proposed
        pairwise as one mask when disjoint, at most ``bridge_gap_px`` apart and within
        this CIE76 distance [Lab units] in mean colour (pieces split by an occluder)
    adjacent_contact_px : the best ``union_pool`` regions are also proposed pairwise as one
        mask when they touch along at least this many work-resolution pixels, whatever their
        colours (the faces of one part lit differently); 0 (default): not proposed
    merge_iou : proposals overlapping more than this are merged (the better-ranked kept)
    max_proposals : at most this many proposals are returned

    Promptable mode
    ---------------
    prompt_erode_px : the silhouette eroded by this much is definite foreground
    prompt_ring_px : the ring this wide around the silhouette is probable background;
        beyond it is definite background (bounds how far the estimate may be off)
    prompt_max_side_px : the GrabCut window is downsampled to at most this long a side
    grabcut_iterations : GrabCut iterations
    prompt_min_area_ratio, prompt_max_ring_fraction : collapse rule, see
        :meth:`ClassicalCameraBackend.prompt`
    """

    work_max_side_px: int = 128
    bilateral_sigma_colour: float = 20.0
    cluster_counts: tuple[int, ...] = (2, 3, 4, 6, 8)
    lightness_weight: float = 0.8
    kmeans_iterations: int = 6
    kmeans_sample_px: int = 2000
    seed: int = 0
    superpixel_spacing_work_px: int = 6
    hierarchy_region_counts: tuple[int, ...] = (32, 20, 12, 8, 5, 3)
    merge_size_exponent: float = 1.0
    canny_low: float = 20.0
    canny_high: float = 50.0
    min_area_px: float = 150.0
    max_area_fraction: float = 0.8
    bridge_gap_px: float = 40.0
    max_hole_fraction: float = 0.25
    union_pool: int = 16
    union_colour_tolerance: float = 20.0
    adjacent_contact_px: int = 0
    merge_iou: float = 0.9
    max_proposals: int = 30
    prompt_erode_px: int = 5
    prompt_ring_px: int = 12
    prompt_max_side_px: int = 160
    grabcut_iterations: int = 2
    prompt_min_area_ratio: float = 0.5
    prompt_max_ring_fraction: float = 0.5

    def __post_init__(self) -> None:
        checks = {
            "work_max_side_px": self.work_max_side_px >= 16,
            "cluster_counts": len(self.cluster_counts) > 0 and all(2 <= k <= 32 for k in self.cluster_counts),
            "kmeans_iterations": self.kmeans_iterations >= 1,
            "kmeans_sample_px": self.kmeans_sample_px >= 64,
            # The region merging keeps dense (n, n) adjacency tables of the superpixels.
            "superpixel_spacing_work_px": self.superpixel_spacing_work_px >= 2
            and (self.work_max_side_px // self.superpixel_spacing_work_px) ** 2 <= 2500,
            "min_area_px": self.min_area_px >= 1,
            "max_area_fraction": 0 < self.max_area_fraction <= 1,
            "merge_iou": 0 < self.merge_iou <= 1,
            "max_proposals": self.max_proposals >= 1,
            "union_pool": self.union_pool >= 0,
            "union_colour_tolerance": self.union_colour_tolerance >= 0,
            "adjacent_contact_px": self.adjacent_contact_px >= 0,
            "prompt_erode_px": self.prompt_erode_px >= 0,
            "prompt_ring_px": self.prompt_ring_px >= 1,
            "prompt_max_side_px": self.prompt_max_side_px >= 16,
            "grabcut_iterations": self.grabcut_iterations >= 1,
            "prompt_min_area_ratio": 0 <= self.prompt_min_area_ratio <= 1,
            "prompt_max_ring_fraction": 0 < self.prompt_max_ring_fraction <= 1,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            values = ", ".join(f"{n}={getattr(self, n)!r}" for n in bad)
            raise ConfigError(f"classical masking backend: option out of range: {values}")

    @staticmethod
    def from_mapping(options: Mapping[str, Any]) -> "ClassicalOptions":
        """Options from a config mapping (``masking.camera.options``): unknown keys are
        rejected with a suggestion, values converted to each field's type."""
        fields = {f.name: f for f in dataclasses.fields(ClassicalOptions)}
        values: dict[str, Any] = {}
        for key, value in options.items():
            if key not in fields:
                close = difflib.get_close_matches(str(key), fields, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ConfigError(f"classical masking backend: unknown option {key!r}{hint}")
            default = fields[key].default
            try:
                if isinstance(default, tuple):
                    values[key] = tuple(int(v) for v in value)
                elif isinstance(default, bool) or not isinstance(default, (int, float)):
                    values[key] = value
                elif isinstance(default, int) and (isinstance(value, float) and not value.is_integer()):
                    raise ValueError("not a whole number")
                else:
                    values[key] = type(default)(value)
            except (TypeError, ValueError) as err:
                raise ConfigError(
                    f"classical masking backend: option {key!r} = {value!r} is not a {type(default).__name__} ({err})"
                ) from err
        return ClassicalOptions(**values)


def _box_of(roi_box, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Search window ``(x0, y0, x1, y1)`` clipped to the image (see ``base.roi_window``)."""
    return roi_window(roi_box, shape)


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    return image


def _kmeans(x: np.ndarray, fit: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> np.ndarray:
    """Labels (n,) int64 of k-means on the rows of ``x`` (n, d) float32.

    Centres are seeded by k-means++ with ``rng`` and fitted by Lloyd iterations on the rows
    ``fit`` (m, d) (a sample of ``x``); then every row of ``x`` goes to its nearest centre.
    """
    sq = np.einsum("ij,ij->i", fit, fit).astype(np.float64)

    def dist2(c: np.ndarray) -> np.ndarray:
        return np.maximum(sq - 2.0 * (fit @ c) + float(c @ c), 0.0)

    centres = [fit[rng.integers(len(fit))]]
    d2 = dist2(centres[0])
    for _ in range(1, k):
        total = float(d2.sum())
        if total <= 0.0:
            break  # fewer distinct colours than k
        centres.append(fit[rng.choice(len(fit), p=d2 / total)])
        d2 = np.minimum(d2, dist2(centres[-1]))
    C = np.stack(centres).astype(np.float32)
    for _ in range(iterations):
        labels = _nearest_centre(fit, C)
        counts = np.bincount(labels, minlength=len(C)).astype(np.float32)
        sums = np.stack([np.bincount(labels, weights=fit[:, j], minlength=len(C)) for j in range(fit.shape[1])], 1)
        C = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1.0)[:, None], C).astype(np.float32)
    return _nearest_centre(x, C)


@njit(cache=True)
def _nearest_centre(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index (n,) int64 of the nearest of ``centres`` (k, d) to each row of ``x`` (n, d).
    (numpy's argmin over a short axis costs ~30x more on a 128x128 window.)"""
    n, d = x.shape
    out = np.empty(n, np.int64)
    for i in range(n):
        best = np.inf
        for c in range(centres.shape[0]):
            acc = 0.0
            for j in range(d):
                diff = x[i, j] - centres[c, j]
                acc += diff * diff
            if acc < best:
                best = acc
                out[i] = c
    return out


def _fill_holes(mask: np.ndarray, max_hole_area: float) -> np.ndarray:
    """``mask`` (h, w) uint8 0/1 with its holes of at most ``max_hole_area`` pixels filled.

    Holes are the inner contours of a two-level contour tree, so a gap open to the window
    border is not a hole. Returns ``mask`` itself when nothing is filled.
    """
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return mask
    holes = [
        c
        for c, (_, _, _, parent) in zip(contours, hierarchy[0])
        if parent >= 0 and cv2.contourArea(c) <= max_hole_area
    ]
    if not holes:
        return mask
    filled = mask.copy()
    cv2.drawContours(filled, holes, -1, 1, thickness=cv2.FILLED)
    return filled


@dataclass
class _Window:
    """The search window of one image, at work resolution.

    box : (x0, y0, x1, y1) in the full image; rgb : (h, w, 3) uint8 smoothed;
    lab : (h, w, 3) float32 CIE Lab; grad : (h, w) float32 Lab gradient [units per work
    pixel]; pixel_area_px : full-image pixels per work pixel; min_area, max_area : proposal
    size limits in work pixels.
    """

    box: tuple[int, int, int, int]
    rgb: np.ndarray
    lab: np.ndarray
    grad: np.ndarray
    pixel_area_px: float
    min_area: float
    max_area: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.rgb.shape[:2]


class _Candidates:
    """Work-resolution candidate masks (h, w) uint8, kept only if their area is plausible."""

    def __init__(self, window: _Window):
        self.window = window
        self.masks: list[np.ndarray] = []
        self._seen: set[bytes] = set()

    def add(self, mask: np.ndarray) -> None:
        m = mask.astype(np.uint8, copy=False)
        if not self.window.min_area <= cv2.countNonZero(m) <= self.window.max_area:
            return
        key = np.packbits(m).tobytes()  # the same region often comes from several k
        if key not in self._seen:
            self._seen.add(key)
            self.masks.append(m)


def _watershed_superpixels(window: _Window, spacing: int) -> np.ndarray:
    """Over-segmentation (h, w) int32 labels 0..n-1: watershed of the colour gradient from
    one seed per ``spacing``-pixel grid cell, placed at the cell's gradient minimum."""
    h, w = window.shape
    grad = window.grad
    spacing = max(1, min(spacing, h, w))  # a window narrower than one cell (at an image border)
    gh, gw = max(h // spacing, 1), max(w // spacing, 1)
    cells = grad[: gh * spacing, : gw * spacing].reshape(gh, spacing, gw, spacing).transpose(0, 2, 1, 3)
    flat = cells.reshape(gh, gw, spacing * spacing).argmin(axis=2)
    rows = (np.arange(gh)[:, None] * spacing + flat // spacing).ravel()
    cols = (np.arange(gw)[None, :] * spacing + flat % spacing).ravel()
    # Pad by one pixel: cv2.watershed claims the image's outer ring as boundary.
    markers = np.zeros((h + 2, w + 2), np.int32)
    markers[rows + 1, cols + 1] = np.arange(1, len(rows) + 1, dtype=np.int32)
    padded = cv2.copyMakeBorder(window.rgb, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    cv2.watershed(padded, markers)
    labels = markers[1:-1, 1:-1]
    # Watershed lines (-1), and the odd pixel it leaves unlabelled (0), go to the
    # 4-neighbour region of the most similar colour.
    for _ in range(8):
        ys, xs = np.nonzero(labels <= 0)
        if len(ys) == 0:
            break
        best = np.full(len(ys), np.inf, np.float32)
        choice = labels[ys, xs].copy()
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ny, nx = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            lab_n = labels[ny, nx]
            d = np.linalg.norm(window.lab[ny, nx] - window.lab[ys, xs], axis=1)
            better = (lab_n > 0) & (d < best)
            best[better], choice[better] = d[better], lab_n[better]
        labels[ys, xs] = choice
    labels[labels <= 0] = 1
    return labels - 1


@njit(cache=True)
def _merge_pair_cost(total, size, edge_sum, edge_count, i, j, size_exponent, base_size):
    """Lab distance of the region means plus the mean gradient on the shared boundary,
    scaled by (harmonic mean size / base_size) ** size_exponent."""
    d = 0.0
    for c in range(3):
        diff = total[i, c] / size[i] - total[j, c] / size[j]
        d += diff * diff
    h = size[i] * size[j] / (size[i] + size[j]) / base_size
    return (np.sqrt(d) + edge_sum[i, j] / edge_count[i, j]) * h ** size_exponent


@njit(cache=True)
def _merge_regions(size, total, edge_sum, edge_count, levels, size_exponent, base_size):
    """Greedy merging of adjacent regions, cheapest pair first.

    size : (n,) float64 pixels per region; total : (n, 3) float64 Lab sums;
    edge_sum, edge_count : (n, n) float64 summed gradient and pixel count of each shared
    boundary (0 where not adjacent); levels : (L,) int64 strictly decreasing region counts
    below n. All four arrays are updated in place.
    Returns (L', n) int64: for each level reached, the region each input region belongs to.
    """
    n = size.shape[0]
    alive = np.ones(n, np.bool_)
    version = np.zeros(n, np.int64)
    parent = np.arange(n)
    heap = [(0.0, 0, 0, 0, 0)]  # typed by its first element, removed below
    heapq.heappop(heap)
    for i in range(n):
        for j in range(i + 1, n):
            if edge_count[i, j] > 0:
                cost = _merge_pair_cost(total, size, edge_sum, edge_count, i, j, size_exponent, base_size)
                heap.append((cost, i, j, 0, 0))
    heapq.heapify(heap)
    out = np.empty((levels.shape[0], n), np.int64)
    reached = 0
    count = n
    while len(heap) > 0 and reached < levels.shape[0]:
        _, i, j, vi, vj = heapq.heappop(heap)
        if not alive[i] or not alive[j] or version[i] != vi or version[j] != vj:
            continue  # stale: one of the regions changed since this pair was queued
        alive[j] = False
        parent[j] = i
        size[i] += size[j]
        for c in range(3):
            total[i, c] += total[j, c]
        version[i] += 1
        for t in range(n):
            if edge_count[j, t] > 0:
                if t != i:
                    edge_sum[i, t] += edge_sum[j, t]
                    edge_count[i, t] += edge_count[j, t]
                    edge_sum[t, i] = edge_sum[i, t]
                    edge_count[t, i] = edge_count[i, t]
                edge_sum[j, t] = 0.0
                edge_count[j, t] = 0.0
                edge_sum[t, j] = 0.0
                edge_count[t, j] = 0.0
        for t in range(n):
            if t != i and edge_count[i, t] > 0:
                a, b = min(i, t), max(i, t)
                cost = _merge_pair_cost(total, size, edge_sum, edge_count, a, b, size_exponent, base_size)
                heapq.heappush(heap, (cost, a, b, version[a], version[b]))
        count -= 1
        if count == levels[reached]:
            for r in range(n):
                root = r
                while parent[root] != root:
                    root = parent[root]
                out[reached, r] = root
            reached += 1
    return out[:reached]


def _merge_hierarchy(
    window: _Window, labels: np.ndarray, levels: tuple[int, ...], size_exponent: float
) -> list[np.ndarray]:
    """Greedy region merging of an over-segmentation ``labels`` (h, w) int 0..n-1; the
    partitions reached at each region count in ``levels``, as (h, w) int region maps.

    The cost of merging two adjacent regions is the Lab distance of their means plus the
    mean gradient along their shared boundary, so regions split by a faint but continuous
    edge (a grey object against a grey finger) merge late. The cost is multiplied by the
    pair's harmonic mean size (relative to the mean superpixel) to the power
    ``size_exponent``, so that small fragments are absorbed before large regions meet.
    """
    n = int(labels.max()) + 1
    wanted = np.array(sorted({int(lv) for lv in levels if 1 <= lv < n}, reverse=True), np.int64)
    if len(wanted) == 0:
        return []
    flat = labels.ravel()
    size = np.bincount(flat, minlength=n).astype(np.float64)
    lab = window.lab.reshape(-1, 3).astype(np.float64)
    total = np.stack([np.bincount(flat, weights=lab[:, j], minlength=n) for j in range(3)], 1)
    # Shared boundaries from horizontally and vertically adjacent pixels of two regions;
    # a pair's strength is the larger gradient of the two pixels.
    g = window.grad
    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    strength = np.concatenate([np.maximum(g[:, :-1], g[:, 1:]).ravel(), np.maximum(g[:-1, :], g[1:, :]).ravel()])
    cut = a != b
    code = a[cut].astype(np.int64) * n + b[cut]
    edge_sum = np.bincount(code, weights=strength[cut], minlength=n * n).reshape(n, n)
    edge_count = np.bincount(code, minlength=n * n).astype(np.float64).reshape(n, n)
    edge_sum += edge_sum.T
    edge_count += edge_count.T
    roots = _merge_regions(size, total, edge_sum, edge_count, wanted, size_exponent, float(size.mean()))
    return [r[labels] for r in roots]


class ClassicalCameraBackend:
    """Camera masking without learned weights (registered as ``'classical'``).

    ``proposals(image, roi_box)`` gives zero-shot candidate masks for Algorithm 1;
    ``prompt(image, prompt_mask)`` refines the CAD silhouette at a converged estimate.
    Both are deterministic: the same image and options give the same masks.
    """

    name = "classical"

    def __init__(self, options: ClassicalOptions | None = None, **overrides: Any):
        """``options``, or keyword overrides of :class:`ClassicalOptions` fields as a
        config file's ``masking.camera.options`` gives them (``get_backend('classical',
        **options)``); unknown or out-of-range options raise ConfigError."""
        if options is None:
            options = ClassicalOptions.from_mapping(overrides)
        elif overrides:
            options = ClassicalOptions.from_mapping({**dataclasses.asdict(options), **overrides})
        self.options = options

    # -- zero-shot proposals -------------------------------------------------------------

    def _window(self, image: np.ndarray, roi_box) -> _Window:
        o = self.options
        x0, y0, x1, y1 = _box_of(roi_box, image.shape[:2])
        crop = image[y0:y1, x0:x1]
        hc, wc = crop.shape[:2]
        s = min(1.0, o.work_max_side_px / max(hc, wc))
        w, h = max(2, int(round(wc * s))), max(2, int(round(hc * s)))
        small = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA) if (w, h) != (wc, hc) else crop
        smooth = cv2.bilateralFilter(np.ascontiguousarray(small), 5, o.bilateral_sigma_colour, 2.0)
        lab = cv2.cvtColor(smooth.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
        gx = cv2.Sobel(lab, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(lab, cv2.CV_32F, 0, 1, ksize=3)
        # A 3x3 Sobel responds 8x the per-pixel slope; report Lab units per pixel.
        grad = np.sqrt((gx * gx + gy * gy).sum(axis=2)) / 8.0
        pixel_area = (wc / w) * (hc / h)
        return _Window(
            box=(x0, y0, x1, y1),
            rgb=smooth,
            lab=lab,
            grad=grad,
            pixel_area_px=pixel_area,
            min_area=o.min_area_px / pixel_area,
            max_area=o.max_area_fraction * w * h,
        )

    def _cluster_candidates(self, window: _Window, out: _Candidates) -> None:
        o = self.options
        h, w = window.shape
        feats = (window.lab * np.array([o.lightness_weight, 1.0, 1.0], np.float32)).reshape(-1, 3)
        rng = np.random.default_rng(o.seed)
        n_px = len(feats)
        fit = feats[np.sort(rng.permutation(n_px)[: o.kmeans_sample_px])] if n_px > o.kmeans_sample_px else feats
        gap = o.bridge_gap_px / np.sqrt(window.pixel_area_px)  # work pixels
        # A square kernel: dilation by it is separable and ~10x faster than by a disk.
        bridge = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * int(np.ceil(gap / 2)) + 1,) * 2)
        small = window.min_area / 4  # fragments smaller than this are noise, not parts
        for k in o.cluster_counts:
            labels = _kmeans(feats, fit, k, rng, o.kmeans_iterations).reshape(h, w)
            for c in range(k):
                m = cv2.morphologyEx((labels == c).astype(np.uint8), cv2.MORPH_OPEN, _CROSS3)
                n, cc, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=4)
                parts = [i for i in range(1, n) if stats[i, 4] >= small]
                for i in parts:
                    if window.min_area <= stats[i, 4] <= window.max_area:
                        out.add(cc == i)
                if len(parts) < 2:
                    continue
                keep = np.zeros(n, bool)
                keep[parts] = True
                pieces = keep[cc].astype(np.uint8)
                ng, groups = cv2.connectedComponents(cv2.dilate(pieces, bridge), connectivity=8)
                member = groups[pieces.astype(bool)]
                owner = cc[pieces.astype(bool)]
                for g in range(1, ng):
                    if len(np.unique(owner[member == g])) >= 2:
                        out.add(pieces.astype(bool) & (groups == g))

    def _watershed_candidates(self, window: _Window, out: _Candidates) -> None:
        o = self.options
        labels = _watershed_superpixels(window, o.superpixel_spacing_work_px)
        for region_map in _merge_hierarchy(window, labels, o.hierarchy_region_counts, o.merge_size_exponent):
            ids, counts = np.unique(region_map, return_counts=True)
            for r, a in zip(ids, counts):
                if window.min_area <= a <= window.max_area:
                    out.add(region_map == r)

    def _edge_candidates(self, window: _Window, out: _Candidates) -> None:
        o = self.options
        gray = cv2.cvtColor(window.rgb, cv2.COLOR_RGB2GRAY)
        edges = cv2.dilate(cv2.Canny(gray, o.canny_low, o.canny_high), _SQUARE3)
        n, cc, stats, _ = cv2.connectedComponentsWithStats((edges == 0).astype(np.uint8), connectivity=4)
        for i in range(1, n):
            # The region lost a band to the dilated edges: give it back (add() checks sizes).
            if 2 * stats[i, 4] >= window.min_area and stats[i, 4] <= window.max_area:
                out.add(cv2.dilate((cc == i).astype(np.uint8), _CROSS3))

    def _rank(self, window: _Window, masks: list[np.ndarray]) -> np.ndarray:
        """Score (N,) of each candidate: mean gradient on its outline over (1 + mean
        gradient inside it), times the share of its outline not on the window border.

        A part stands out from its surroundings and is smooth inside; background runs out
        of the window and texture is busy inside.
        """
        g_edge = cv2.dilate(window.grad, _SQUARE3)  # the edge may sit just outside the outline
        h, w = window.shape
        scores = np.zeros(len(masks))
        for n, m in enumerate(masks):
            x, y, bw, bh = cv2.boundingRect(m)
            if bw == 0:
                continue
            # Work on the bounding box plus a one-pixel frame where that stays in the window.
            x0, y0, x1, y1 = max(x - 1, 0), max(y - 1, 0), min(x + bw + 1, w), min(y + bh + 1, h)
            sub = m[y0:y1, x0:x1]
            inner = cv2.erode(sub, _SQUARE3)  # pixels outside the window count as set
            outline = sub - inner
            length = cv2.countNonZero(outline)
            on_border = (
                (cv2.countNonZero(sub[0]) if y0 == 0 else 0)
                + (cv2.countNonZero(sub[-1]) if y1 == h else 0)
                + (cv2.countNonZero(sub[:, 0]) if x0 == 0 else 0)
                + (cv2.countNonZero(sub[:, -1]) if x1 == w else 0)
            )
            if length == 0:
                continue
            contrast = cv2.mean(g_edge[y0:y1, x0:x1], mask=outline)[0]
            texture = cv2.mean(window.grad[y0:y1, x0:x1], mask=inner)[0] if cv2.countNonZero(inner) else contrast
            scores[n] = length / (length + on_border) * contrast / (1.0 + texture)
        return scores

    def proposals(self, image: np.ndarray, roi_box=None) -> list[np.ndarray]:
        """Zero-shot candidate object masks in the search window of ``image``.

        image : (H, W, 3) uint8 RGB
        roi_box : where the object can be: ``(x0, y0, x1, y1)`` half-open pixel columns and
            rows (e.g. the pose belief projected into the image), an object with ``x0, y0,
            width, height`` (a :class:`~mvtop_cli.render.roi.Roi`), a
            :class:`~mvtop_cli.masking.base.MaskContext` (its ``roi_box``), or None for the
            whole image
        Returns at most ``max_proposals`` (H, W) bool masks, best-ranked first, each inside
        the window, of plausible area, no two with IoU above ``merge_iou``.
        """
        image = _check_image(image)
        o = self.options
        window = self._window(image, roi_box)
        cands = _Candidates(window)
        self._cluster_candidates(window, cands)
        self._watershed_candidates(window, cands)
        self._edge_candidates(window, cands)
        if not cands.masks:
            return []
        masks = cands.masks
        scores = self._rank(window, masks)
        order = np.argsort(-scores, kind="stable")
        top = [int(order[i]) for i in _dedup([masks[i] for i in order], o.merge_iou, o.max_proposals)]
        pool = [masks[i] for i in top[: o.union_pool]]
        extra = self._occluder_unions(window, pool) + self._adjacent_unions(window, pool)
        masks = [masks[i] for i in top] + extra
        scores = np.concatenate([scores[top], self._rank(window, extra)])
        order = np.argsort(-scores, kind="stable")
        kept = [masks[order[i]] for i in _dedup([masks[i] for i in order], o.merge_iou, o.max_proposals)]
        # Fill holes (a highlight inside a part) only now: it is the costly step per mask.
        filled = [_fill_holes(m, o.max_hole_fraction * cv2.countNonZero(m)) for m in kept]
        filled = [f for f in filled if cv2.countNonZero(f) <= window.max_area]
        kept = [filled[i] for i in _dedup(filled, o.merge_iou, o.max_proposals)]
        return [_paste(m, window.box, image.shape[:2]) for m in kept]

    def _occluder_unions(self, window: _Window, masks: list[np.ndarray]) -> list[np.ndarray]:
        """Unions of two disjoint regions of similar median colour at most ``bridge_gap_px``
        apart: the visible pieces of a part cut in two by an occluder of any colour (the
        in-cluster bridging of :meth:`_cluster_candidates` misses an occluder that shares
        the part's colour cluster, e.g. a grey part under a grey finger). The median keeps
        a highlight on one piece from separating the two."""
        o = self.options
        if len(masks) < 2:
            return []
        gap = o.bridge_gap_px / np.sqrt(window.pixel_area_px)
        areas = np.array([cv2.countNonZero(m) for m in masks])
        boxes = np.array([cv2.boundingRect(m) for m in masks], np.float64)  # x, y, w, h
        lo, hi = boxes[:, :2], boxes[:, :2] + boxes[:, 2:]
        # Pairs that fit the size limit and whose boxes are at most the gap apart.
        separation = (np.maximum(lo[:, None], lo[None]) - np.minimum(hi[:, None], hi[None])).max(axis=2)
        fits = (areas[:, None] + areas[None]) <= window.max_area
        pairs = np.argwhere(np.triu(fits & (separation <= gap), k=1))
        if len(pairs) == 0:
            return []
        # Median colour on every other pixel and row: robust to a highlight, and cheap.
        lab2 = window.lab[::2, ::2]

        def median_colour(m: np.ndarray) -> np.ndarray:
            pixels = lab2[m[::2, ::2] > 0]
            return np.median(pixels if len(pixels) else window.lab[m > 0], axis=0)

        medians = np.array([median_colour(m) for m in masks])
        close = np.linalg.norm(medians[pairs[:, 0]] - medians[pairs[:, 1]], axis=1) <= o.union_colour_tolerance
        grown: dict[int, np.ndarray] = {}
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * int(np.ceil(gap)) + 1,) * 2)
        out = []
        for i, j in pairs[close].tolist():
            if cv2.countNonZero(masks[i] & masks[j]) > 0.05 * min(areas[i], areas[j]):
                continue
            if i not in grown:
                grown[i] = cv2.dilate(masks[i], kernel)
            if cv2.countNonZero(grown[i] & masks[j]):
                out.append(masks[i] | masks[j])
        return out

    def _adjacent_unions(self, window: _Window, masks: list[np.ndarray]) -> list[np.ndarray]:
        """Unions of two regions that touch along at least ``adjacent_contact_px`` pixels
        (8-connected) and barely overlap, whatever their colours: the faces of one part lit
        differently, which colour, watershed and edges all split (a plug's bright front and
        shaded side face, on its frame 0: the best single proposal covered half the part, IoU
        0.48-0.51 with its silhouette, the union 0.86-0.94). Which union is the part is left
        to the poses that choose among the proposals (Algorithm 1-2)."""
        o = self.options
        if o.adjacent_contact_px <= 0 or len(masks) < 2:
            return []
        areas = [cv2.countNonZero(m) for m in masks]
        grown = [cv2.dilate(m, _SQUARE3) for m in masks]
        out = []
        for i in range(len(masks)):
            for j in range(i + 1, len(masks)):
                if areas[i] + areas[j] > window.max_area:
                    continue
                if cv2.countNonZero(masks[i] & masks[j]) > 0.05 * min(areas[i], areas[j]):
                    continue  # nested or overlapping: another segmentation of the same region
                if cv2.countNonZero(grown[i] & masks[j]) >= o.adjacent_contact_px:
                    out.append(masks[i] | masks[j])
        return out

    # -- promptable mode -----------------------------------------------------------------

    def prompt(self, image: np.ndarray, prompt_mask: np.ndarray, roi_box=None) -> np.ndarray:
        """Refine a rendered CAD silhouette into the observed object mask with GrabCut.

        image : (H, W, 3) uint8 RGB
        prompt_mask : (H, W) bool, the object rendered at the current estimate
        roi_box : unused (the window follows the prompt); accepted for symmetry with
            :meth:`proposals`
        Returns (H, W) bool.

        GrabCut runs in a window around the prompt, initialised as: the silhouette eroded
        by ``prompt_erode_px`` definite foreground, the rest of it probable foreground, a
        ``prompt_ring_px`` ring around it probable background, everything further
        definite background. Only result components touching the silhouette are kept.
        Collapse rule: the prompt itself is returned when GrabCut fails, keeps less than
        ``prompt_min_area_ratio`` of the prompt's area, or claims more than
        ``prompt_max_ring_fraction`` of the probable-background ring (the object cannot
        be that far off a converged estimate, so the colour models have leaked).
        """
        del roi_box
        image = _check_image(image)
        o = self.options
        prompt = np.asarray(prompt_mask, dtype=bool)
        if prompt.shape != image.shape[:2]:
            raise ValueError(f"prompt mask {prompt.shape} does not match image {image.shape[:2]}")
        ys, xs = np.nonzero(prompt)
        if len(ys) == 0:
            return np.zeros_like(prompt)
        H, W = prompt.shape
        margin = o.prompt_ring_px + 4
        x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, W)
        y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, H)
        crop = image[y0:y1, x0:x1]
        hc, wc = crop.shape[:2]
        s = min(1.0, o.prompt_max_side_px / max(hc, wc))
        w, h = max(2, int(round(wc * s))), max(2, int(round(hc * s)))
        p_crop = prompt[y0:y1, x0:x1].astype(np.float32)
        if (w, h) != (wc, hc):
            img = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
            p = (cv2.resize(p_crop, (w, h), interpolation=cv2.INTER_AREA) >= 0.5).astype(np.uint8)
        else:
            img, p = np.ascontiguousarray(crop), p_crop.astype(np.uint8)
        erode_r = int(round(o.prompt_erode_px * s))
        ring_r = max(1, int(round(o.prompt_ring_px * s)))
        core = cv2.erode(p, _disk(erode_r)) if erode_r > 0 else p
        grown = cv2.dilate(p, _disk(ring_r))
        gc = np.full((h, w), _BGD, np.uint8)
        gc[grown > 0] = _PR_BGD
        gc[p > 0] = _PR_FGD
        gc[core > 0] = _FGD
        fallback = prompt.copy()
        try:
            # GrabCut seeds its colour models with k-means on OpenCV's RNG: fix it so that
            # a call's result depends only on its inputs.
            cv2.setRNGSeed(o.seed)
            cv2.grabCut(img, gc, None, np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64),
                        o.grabcut_iterations, cv2.GC_INIT_WITH_MASK)
        except cv2.error:
            return fallback  # degenerate window (e.g. no background samples)
        fg = ((gc == _FGD) | (gc == _PR_FGD)).astype(np.uint8)
        seed = core if cv2.countNonZero(core) else p
        n, cc = cv2.connectedComponents(fg, connectivity=4)
        touching = np.unique(cc[(seed > 0) & (fg > 0)])
        fg = np.isin(cc, touching[touching > 0]).astype(np.uint8)
        ring = (grown > 0) & (p == 0)
        area, p_area = cv2.countNonZero(fg), cv2.countNonZero(p)
        if area < o.prompt_min_area_ratio * p_area or np.count_nonzero(fg.astype(bool) & ring) > (
            o.prompt_max_ring_fraction * np.count_nonzero(ring)
        ):
            return fallback
        return _paste(fg, (x0, y0, x1, y1), (H, W))


def _dedup(masks: list[np.ndarray], merge_iou: float, limit: int) -> list[int]:
    """Indices of the first ``limit`` of ``masks`` (same shape, in order) that overlap no
    earlier kept mask with IoU above ``merge_iou`` (greedy NMS with rank as the score)."""
    if not masks:
        return []
    order_scores = -np.arange(len(masks), dtype=np.float64)
    return [int(i) for i in mask_nms(np.stack(masks), order_scores, merge_iou)[:limit]]


def _paste(mask: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int]) -> np.ndarray:
    """Work-resolution ``mask`` (h, w) -> (H, W) bool full-image mask, resized (bilinear,
    thresholded at one half) onto ``box`` = (x0, y0, x1, y1) and empty elsewhere."""
    x0, y0, x1, y1 = box
    out = np.zeros(shape, bool)
    if mask.shape != (y1 - y0, x1 - x0):
        up = cv2.resize(mask.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
        out[y0:y1, x0:x1] = up >= 0.5
    else:
        out[y0:y1, x0:x1] = mask.astype(bool)
    return out
