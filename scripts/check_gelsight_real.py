"""Check the tactile difference mask on real GelSight R1.5 presses (Taxim data set).

For each of the 49 presses of a 4 mm ball, the contact mask's centroid and equivalent
radius sqrt(area / pi) are compared with the hand-labelled contact circle.

Usage: .venv/bin/python scripts/check_gelsight_real.py [path/to/dataPack_small.npz]
(default: ../shared/data/real/gelsight_taxim/dataPack_small.npz beside the checkout).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mvtop_cli.masking.base import MaskContext
from mvtop_cli.masking.tactile import TactileDifferenceBackend, TactileMaskParams, change_magnitude

MM_PER_PX = 0.1245  # Taxim data set at 120x160 (README beside the data)
DEFAULT_DATA = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "gelsight_taxim" / "dataPack_small.npz"
)


def press_errors(data_path: Path, params: TactileMaskParams = TactileMaskParams()) -> dict[str, np.ndarray]:
    """Per-press centroid error [px], signed radius error [px] and mask area [px].

    Returns arrays of shape (49,): ``centroid_px`` (Euclidean distance of the mask centroid
    to the labelled centre), ``radius_px`` (equivalent radius minus labelled radius),
    ``area_px``, ``label_radius_px``; and ``offset_px`` (49, 2), the centroid minus the
    labelled centre (x, y). A press with an empty mask gets ``inf`` / ``nan`` errors.
    """
    with np.load(data_path) as data:
        background = data["f0"]
        images = data["imgs"]
        centres = data["touch_center"].astype(np.float64)  # (49, 2) pixel (x, y)
        radii = data["touch_radius"].astype(np.float64)
    backend = TactileDifferenceBackend(params)
    context = MaskContext(background=background)
    centroid, radius, area, offset = [], [], [], []
    for image, centre, label_radius in zip(images, centres, radii):
        mask = backend.contact_mask(image, context)
        n = int(mask.sum())
        area.append(n)
        if n == 0:
            centroid.append(np.inf)
            radius.append(np.inf)
            offset.append((np.nan, np.nan))
            continue
        rows, cols = np.nonzero(mask)
        offset.append((cols.mean() - centre[0], rows.mean() - centre[1]))
        centroid.append(float(np.hypot(*offset[-1])))
        radius.append(float(np.sqrt(n / np.pi) - label_radius))
    return {
        "centroid_px": np.array(centroid),
        "radius_px": np.array(radius),
        "area_px": np.array(area),
        "label_radius_px": radii,
        "offset_px": np.array(offset),
    }


def label_offsets(data_path: Path, params: TactileMaskParams = TactileMaskParams()) -> np.ndarray:
    """(49, 2) offset [px] (x, y) of circles fitted to each press's ring of strongest
    colour change from the labelled centres: a check of the labels that does not use the
    mask. Along 72 rays from the labelled centre the change magnitude's maximum between 5
    and 25 px is taken; a least-squares circle through those points gives the centre."""
    from scipy import ndimage

    with np.load(data_path) as data:
        background, images = data["f0"], data["imgs"]
        centres = data["touch_center"].astype(np.float64)
    offsets = []
    steps = np.arange(5.0, 25.0, 0.5)
    for image, (cx, cy) in zip(images, centres):
        magnitude, _ = change_magnitude(image, background, params.blur_sigma_px, params.subtract_median_offset)
        points = []
        for angle in np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False):
            xs, ys = cx + steps * np.cos(angle), cy + steps * np.sin(angle)
            if xs.min() < 0 or ys.min() < 0 or xs.max() > magnitude.shape[1] - 1 or ys.max() > magnitude.shape[0] - 1:
                continue  # the ray leaves the image
            j = int(np.argmax(ndimage.map_coordinates(magnitude, [ys, xs], order=1)))
            points.append((xs[j], ys[j]))
        pts = np.array(points)
        # x^2 + y^2 = 2 a x + 2 b y + c, centre (a, b).
        design = np.column_stack([2.0 * pts, np.ones(len(pts))])
        a, b, _ = np.linalg.lstsq(design, (pts**2).sum(axis=1), rcond=None)[0]
        offsets.append((a - cx, b - cy))
    return np.array(offsets)


def main(argv: list[str]) -> int:
    path = Path(argv[1]) if len(argv) > 1 else DEFAULT_DATA
    if not path.is_file():
        print(f"{path}: not found (the Taxim data is expected in ../shared/data/real beside the checkout)",
              file=sys.stderr)
        return 2
    errors = press_errors(path)
    c, r = errors["centroid_px"], errors["radius_px"]
    print(f"{path}: {len(c)} presses, {MM_PER_PX} mm/px")
    print(f"centroid error  median {np.median(c):.2f} px ({np.median(c) * MM_PER_PX:.3f} mm), "
          f"90th pct {np.percentile(c, 90):.2f} px, max {c.max():.2f} px ({c.max() * MM_PER_PX:.3f} mm)")
    print(f"radius error    median {np.median(r):+.2f} px ({np.median(r) * MM_PER_PX:+.3f} mm), "
          f"median |.| {np.median(np.abs(r)):.2f} px ({np.median(np.abs(r)) * MM_PER_PX:.3f} mm), "
          f"range [{r.min():+.2f}, {r.max():+.2f}] px")
    area_mm2 = errors["area_px"] * MM_PER_PX**2
    label_mm2 = np.pi * (errors["label_radius_px"] * MM_PER_PX) ** 2
    print(f"contact area    median {np.median(area_mm2):.2f} mm^2 "
          f"(labelled circles: median {np.median(label_mm2):.2f} mm^2)")
    mask_offset = np.nanmedian(errors["offset_px"], axis=0)
    print(f"mask offset     centroids sit ({mask_offset[0]:+.2f}, {mask_offset[1]:+.2f}) px "
          "from the labelled centres (median)")
    offsets = label_offsets(path)
    median = np.median(offsets, axis=0)
    print(f"label check     rim circles sit ({median[0]:+.2f}, {median[1]:+.2f}) px from the labelled centres "
          f"(median; {np.hypot(*median):.2f} px), independent of the mask")
    to_rim = np.hypot(*(errors["offset_px"] - offsets).T)
    print(f"                mask centroid to rim-circle centre: median {np.nanmedian(to_rim):.2f} px, "
          f"max {np.nanmax(to_rim):.2f} px")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
