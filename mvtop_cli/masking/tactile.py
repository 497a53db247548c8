"""Tactile masking backend: contact regions of a GelSight-style image (paper section IV-A).

Two sources of the contact region:

- **difference**: the colour change against the sensor's no-contact frame. The per-pixel
  change is smoothed, and a pixel is a *detection* when its change magnitude exceeds
  ``noise_threshold_sigmas`` robust standard deviations of the change over the image
  (the background's noise; contact covers well under half of the gel). Each connected
  detection is then cut at **half of its own peak response** above the image's typical
  level: a blurred edge lies where the response has fallen to half its height, the
  classic full-width-at-half-maximum rule, and taking the peak per detection keeps a
  weak contact beside a strong one. Closing, hole filling (the flat middle of a press
  does not change colour) and, by default, the convex hull (a convex body on a flat gel
  touches it in a convex patch; where the rim's colour matches the background, e.g. a
  saturated red LED corner, the ring of response is open and hole filling alone fails)
  give one region per contact; regions smaller than ``min_area_px`` are dropped. Each
  region's *evidence* is its summed change above the detection threshold.
- **depth**: when the sensor publishes its indentation (metres, 0 = undeformed), the
  contact is exactly ``indentation_m > depth_threshold_m``.

``mode`` chooses: ``'depth'`` (the depth when given, else the difference),
``'difference'`` (always the image), or ``'refine'`` (the paper's refinement: undeformed
pixels, ``indentation_m <= depth_threshold_m``, are removed from the change magnitude
before binarising, and from the result).

On the 49 real GelSight R1.5 presses of the Taxim data set (4 mm ball), the default
parameters give a median centroid error of 2.6 px (0.32 mm, max 4.7 px) and a median
radius error of +1.5 px (0.19 mm) against the hand-labelled contact circles; most of the
centroid error is an offset of the labels themselves (circles fitted to the ring of
strongest change sit 1.9 px from them). See ``scripts/check_gelsight_real.py``. No
parameter was tuned per image: the cut is the half maximum by the rule above, the
detection threshold a noise multiple; only ``min_relative_evidence`` was set with the
real frames in view (see there). Like any image-based mask, the region
includes the narrow band where the gel deforms around the contact (on simulated flat
faces ~2.8 px, about 1.2x the combined gel and smoothing blur); mode 'refine' removes it.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from mvtop_cli.errors import ConfigError, EstimationError
from mvtop_cli.masking.base import MaskContext, split_prompt

# Scale from the median absolute deviation to the standard deviation of a Gaussian.
_MAD_TO_STD = 1.4826
_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)
_MODES = ("depth", "difference", "refine")


@dataclass(frozen=True)
class TactileMaskParams:
    """Parameters of :class:`TactileDifferenceBackend` (config ``masking.tactile.options``).

    mode : 'depth' | 'difference' | 'refine'
        Which source gives the mask (see the module docstring).
    depth_threshold_m : float
        Indentation [m] above which a pixel is in contact (0.02 mm: above rendering
        round-off, well below the presses that visibly change a GelSight image).
    blur_sigma_px : float
        Gaussian smoothing of the colour change [px] before thresholding.
    noise_threshold_sigmas : float
        Detection threshold in robust standard deviations of the change. For 3-channel
        Gaussian noise the magnitude exceeds 5 sigma with probability ~1e-5 per pixel.
    min_difference_dn : float
        Lower bound of the detection threshold [DN], for noise-free or quantised images
        whose robust deviation is ~0.
    peak_fraction : float
        A detection is cut where its response falls below this fraction of its peak
        above the image's median change (0.5: half maximum, see the module docstring).
    subtract_median_offset : bool
        Remove the per-channel median change first (a global illumination drift between
        the no-contact frame and the image; valid while contact covers < half the gel).
    opening_radius_px, closing_radius_px : int
        Morphological opening of the detections (drops isolated noise pixels) and closing
        of each contact region before hole filling [px]; 0 disables.
    convex_hull : bool
        Replace each contact region by its convex hull.
    min_area_px : int
        Smallest contact region kept from the difference image [px].
    min_relative_evidence : float
        ``contact_mask`` keeps the difference regions whose evidence is at least this
        fraction of the strongest region's. All regions stay proposals. On the real Taxim
        presses, regions from the background's interference rings reach at most 5 % of
        the press's evidence, so 0.25 leaves a 5x margin while keeping a second contact
        of comparable strength.
    """

    mode: str = "depth"
    depth_threshold_m: float = 2e-5
    blur_sigma_px: float = 1.0
    noise_threshold_sigmas: float = 5.0
    min_difference_dn: float = 2.0
    peak_fraction: float = 0.5
    subtract_median_offset: bool = True
    opening_radius_px: int = 1
    closing_radius_px: int = 2
    convex_hull: bool = True
    min_area_px: int = 20
    min_relative_evidence: float = 0.25

    def __post_init__(self) -> None:
        problems = []
        if self.mode not in _MODES:
            close = difflib.get_close_matches(str(self.mode), _MODES, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            problems.append(f"mode {self.mode!r} is not one of {', '.join(_MODES)}{hint}")
        for name in ("depth_threshold_m", "blur_sigma_px", "noise_threshold_sigmas", "min_difference_dn"):
            if not getattr(self, name) >= 0:
                problems.append(f"{name} = {getattr(self, name)!r} must be >= 0")
        if not 0.0 <= self.min_relative_evidence <= 1.0:
            problems.append(f"min_relative_evidence = {self.min_relative_evidence!r} must be in [0, 1]")
        if not 0.0 < self.peak_fraction < 1.0:
            problems.append(f"peak_fraction = {self.peak_fraction!r} must be in (0, 1)")
        for name in ("opening_radius_px", "closing_radius_px", "min_area_px"):
            if getattr(self, name) < 0:
                problems.append(f"{name} = {getattr(self, name)!r} must be >= 0")
        if problems:
            raise ConfigError(f"difference masking backend: {'; '.join(problems)}")

    @staticmethod
    def from_mapping(options: Mapping[str, Any]) -> TactileMaskParams:
        """Parameters from a config's options; ConfigError for unknown keys or wrong types."""
        fields = {f.name: f for f in dataclasses.fields(TactileMaskParams)}
        values: dict[str, Any] = {}
        for key, value in options.items():
            if key not in fields:
                close = difflib.get_close_matches(str(key), fields, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ConfigError(f"difference masking backend: unknown option {key!r}{hint}")
            default = fields[key].default
            if isinstance(default, bool):
                ok = isinstance(value, bool)
            elif isinstance(default, int):
                ok = isinstance(value, int) and not isinstance(value, bool)
            elif isinstance(default, float):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                value = float(value) if ok else value
            else:
                ok = isinstance(value, type(default))
            if not ok:
                raise ConfigError(
                    f"difference masking backend: option {key!r} = {value!r} is not of type {type(default).__name__}"
                )
            values[key] = value
        return TactileMaskParams(**values)


def depth_mask(indentation_m: np.ndarray, depth_threshold_m: float) -> np.ndarray:
    """Contact pixels from an indentation map: ``indentation_m > depth_threshold_m``.

    indentation_m : (H, W) float [m], 0 = undeformed. Returns (H, W) bool.
    """
    indentation = np.asarray(indentation_m)
    if indentation.ndim != 2:
        raise ValueError(f"indentation_m must be (H, W), got shape {indentation.shape}")
    return indentation > depth_threshold_m


def change_magnitude(
    image: np.ndarray,
    background: np.ndarray,
    blur_sigma_px: float = 1.0,
    subtract_median_offset: bool = True,
) -> tuple[np.ndarray, float]:
    """Smoothed colour change against the no-contact frame, and its robust noise level.

    Parameters
    ----------
    image, background : (H, W, C) or (H, W) numeric, same shape
    blur_sigma_px : float
        Gaussian smoothing of each channel's change [px]; 0 disables.
    subtract_median_offset : bool
        Remove each channel's median change (global illumination drift).

    Returns
    -------
    magnitude : (H, W) float32
        Euclidean norm of the smoothed change over the channels [DN].
    noise_std : float
        Robust standard deviation of the smoothed per-channel change [DN]
        (1.4826 x median absolute deviation, pooled over channels).
    """
    img = np.asarray(image, dtype=np.float32)
    ref = np.asarray(background, dtype=np.float32)
    if img.ndim == 2:
        img, ref = img[..., None], ref[..., None]
    change = img - ref
    channels = change.reshape(-1, change.shape[-1])
    if subtract_median_offset:
        change = change - np.median(channels, axis=0)
    if blur_sigma_px > 0:
        change = cv2.GaussianBlur(change, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
        change = change.reshape(img.shape)  # cv2 drops a single channel axis
    channels = change.reshape(-1, change.shape[-1])
    deviation = np.abs(channels - np.median(channels, axis=0))
    noise_std = _MAD_TO_STD * float(np.median(deviation))
    magnitude = np.sqrt(np.sum(change * change, axis=-1)).astype(np.float32)
    return magnitude, noise_std


def difference_components(
    image: np.ndarray,
    background: np.ndarray,
    params: TactileMaskParams = TactileMaskParams(),
    deformed: np.ndarray | None = None,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Contact regions from the change against the no-contact frame, strongest first.

    Parameters
    ----------
    image, background : (H, W, 3) uint8 (or any numeric, same shape)
    params : TactileMaskParams
    deformed : (H, W) bool or None
        Pixels the depth says are deformed; the others are removed before binarising
        and from the result (the paper's depth refinement).

    Returns
    -------
    regions : list of K (H, W) bool
        Disjoint 8-connected regions of at least ``min_area_px`` pixels.
    evidence : (K,) float64
        Summed change magnitude above the detection threshold over each region [DN px],
        in decreasing order.
    """
    p = params
    magnitude, noise_std = change_magnitude(image, background, p.blur_sigma_px, p.subtract_median_offset)
    noise_level = max(p.noise_threshold_sigmas * noise_std, p.min_difference_dn)
    typical = float(np.median(magnitude))
    if deformed is not None:
        magnitude = np.where(deformed, magnitude, 0.0).astype(np.float32)

    detections = magnitude > noise_level
    if p.opening_radius_px > 0:
        detections = ndimage.binary_opening(detections, _disk(p.opening_radius_px))
    labels, _ = ndimage.label(detections, _EIGHT_CONNECTED)
    shape = detections.shape
    merged = np.zeros(shape, dtype=bool)
    pad = p.closing_radius_px + 1
    for index, window in enumerate(ndimage.find_objects(labels), start=1):
        if window is None:
            continue
        # Work in the detection's bounding box, grown by the closing radius.
        rows = slice(max(window[0].start - pad, 0), min(window[0].stop + pad, shape[0]))
        cols = slice(max(window[1].start - pad, 0), min(window[1].stop + pad, shape[1]))
        detection = labels[rows, cols] == index
        if np.count_nonzero(detection) < p.min_area_px:
            continue
        local = magnitude[rows, cols]
        peak = float(local[detection].max())
        level = max(noise_level, typical + p.peak_fraction * (peak - typical))
        merged[rows, cols] |= _close_fill_hull(detection & (local > level), p.closing_radius_px, p.convex_hull)
    if deformed is not None:
        merged &= deformed
    regions = _components(merged, p.min_area_px)
    excess = np.maximum(magnitude.astype(np.float64) - noise_level, 0.0)
    evidence = np.array([excess[region].sum() for region in regions], dtype=np.float64)
    order = np.argsort(-evidence, kind="stable")
    return [regions[i] for i in order], evidence[order]


class TactileDifferenceBackend:
    """Tactile masking backend, registered as ``'difference'`` (the config default).

    ``proposals`` gives each contact region (strongest first) and, when there are several,
    their union, for Algorithm 1 to pick from; ``contact_mask`` the single best mask;
    ``prompt`` the regions the prompt mask overlaps or the prompt points fall in. The
    context must carry ``background`` (the no-contact frame) unless the mask comes from
    ``indentation_m`` alone (mode 'depth' with a depth topic).
    """

    name = "difference"

    def __init__(self, params: TactileMaskParams | None = None, **overrides: Any):
        """``params``, or keyword overrides of :class:`TactileMaskParams` fields as a config
        file's ``masking.tactile.options`` gives them (``get_backend('difference', **options)``);
        unknown options, wrong types or out-of-range values raise ConfigError."""
        if params is None:
            params = TactileMaskParams.from_mapping(overrides)
        elif overrides:
            params = TactileMaskParams.from_mapping({**dataclasses.asdict(params), **overrides})
        self.params = params

    def components(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """Disjoint contact regions, each (H, W) bool, strongest first; [] when nothing touches."""
        return self._regions(image, context)[0]

    def proposals(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """Each contact region, then their union when there are several; [] if none."""
        parts = self.components(image, context)
        if len(parts) > 1:
            parts.append(np.logical_or.reduce(parts))
        return parts

    def contact_mask(self, image: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """The single best contact mask, (H, W) bool (all False when nothing touches).

        From the depth, every pixel indented beyond ``depth_threshold_m`` (a measurement
        has no spurious regions). From the image, the regions with at least
        ``min_relative_evidence`` of the strongest region's evidence.
        """
        parts, evidence = self._regions(image, context)
        mask = np.zeros(np.asarray(image).shape[:2], dtype=bool)
        for i, part in enumerate(parts):
            if evidence is None or evidence[i] >= self.params.min_relative_evidence * evidence.max():
                mask |= part
        return mask

    def prompt(self, image: np.ndarray, prompt: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """Union of the contact regions that the prompt mask overlaps or a prompt point
        ``(x, y)`` [px] falls in, (H, W) bool."""
        shape = np.asarray(image).shape[:2]
        prompt_mask, points = split_prompt(prompt, shape)
        if points is not None:
            prompt_mask = np.zeros(shape, dtype=bool)
            cols = np.rint(points[:, 0]).astype(int)
            rows = np.rint(points[:, 1]).astype(int)
            ok = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
            prompt_mask[rows[ok], cols[ok]] = True
        selected = np.zeros(shape, dtype=bool)
        for part in self.components(image, context):
            if np.any(part & prompt_mask):
                selected |= part
        return selected

    def _regions(self, image: np.ndarray, context: MaskContext | None) -> tuple[list[np.ndarray], np.ndarray | None]:
        """Regions and their evidence (see ``difference_components``); None from the depth."""
        context = context if context is not None else MaskContext()
        image = np.asarray(image)
        shape = image.shape[:2]
        p = self.params
        indentation = context.indentation_m
        if indentation is not None:
            indentation = np.asarray(indentation)
            if indentation.shape != shape:
                raise EstimationError(
                    f"tactile indentation map is {indentation.shape}, the image is {shape}: they must match"
                )
        if p.mode == "depth" and indentation is not None:
            parts: list[np.ndarray] = _components(depth_mask(indentation, p.depth_threshold_m), min_area_px=0)
            evidence = None
        else:
            background = context.background
            if background is None:
                raise EstimationError(
                    "tactile difference mask needs the sensor's no-contact frame (context.background); none given"
                )
            background = np.asarray(background)
            if background.shape != image.shape:
                raise EstimationError(
                    f"tactile no-contact frame is {background.shape}, the image is {image.shape}: they must match"
                )
            deformed = None
            if p.mode == "refine" and indentation is not None:
                deformed = depth_mask(indentation, p.depth_threshold_m)
            parts, evidence = difference_components(image, background, p, deformed)
        if context.roi_box is not None:
            x0, y0, x1, y1 = (max(int(v), 0) for v in context.roi_box)
            inside = np.zeros(shape, dtype=bool)
            inside[y0:y1, x0:x1] = True
            keep = [i for i, part in enumerate(parts) if np.any(part & inside)]
            parts = [parts[i] & inside for i in keep]
            if evidence is not None:
                evidence = evidence[keep]
        return parts, evidence


def _disk(radius_px: int) -> np.ndarray:
    r = int(radius_px)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return xx * xx + yy * yy <= r * r


def _close_fill_hull(region: np.ndarray, closing_radius_px: int, convex_hull: bool) -> np.ndarray:
    """Close (without eroding at the window edge), fill holes and optionally take the hull."""
    if not region.any():
        return region
    if closing_radius_px > 0:
        r = closing_radius_px
        padded = np.pad(region, r)
        region = ndimage.binary_closing(padded, _disk(r))[r:-r, r:-r]
    region = ndimage.binary_fill_holes(region)
    if not convex_hull:
        return region
    # One hull over all pieces: they come from one connected detection, one contact.
    rows, cols = np.nonzero(region)
    points = np.stack([cols, rows], axis=1).astype(np.int32)
    hull = np.zeros(region.shape, dtype=np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(points), 1)
    return hull.astype(bool) | region


def _components(mask: np.ndarray, min_area_px: int) -> list[np.ndarray]:
    """8-connected components of ``mask`` with at least ``min_area_px`` pixels, largest first."""
    labels, count = ndimage.label(mask, _EIGHT_CONNECTED)
    if count == 0:
        return []
    areas = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    order = [i for i in np.argsort(-areas, kind="stable") if areas[i] >= min_area_px]
    return [labels == i + 1 for i in order]
