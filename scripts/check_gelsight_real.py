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
from mvtop_cli.masking.tactile import TactileDifferenceBackend, TactileMaskParams

MM_PER_PX = 0.1245  # Taxim data set at 120x160 (README beside the data)
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "gelsight_taxim" / "dataPack_small.npz"


def press_errors(data_path: Path, params: TactileMaskParams = TactileMaskParams()) -> dict[str, np.ndarray]:
    """Per-press centroid error [px], signed radius error [px] and mask area [px].

    Returns arrays of shape (49,): ``centroid_px`` (Euclidean distance of the mask centroid
    to the labelled centre), ``radius_px`` (equivalent radius minus labelled radius),
    ``area_px``; a press with an empty mask gets ``inf`` centroid and radius errors.
    """
    with np.load(data_path) as data:
        background = data["f0"]
        images = data["imgs"]
        centres = data["touch_center"].astype(np.float64)  # (49, 2) pixel (x, y)
        radii = data["touch_radius"].astype(np.float64)
    backend = TactileDifferenceBackend(params)
    context = MaskContext(background=background)
    centroid, radius, area = [], [], []
    for image, centre, label_radius in zip(images, centres, radii):
        mask = backend.contact_mask(image, context)
        n = int(mask.sum())
        area.append(n)
        if n == 0:
            centroid.append(np.inf)
            radius.append(np.inf)
            continue
        rows, cols = np.nonzero(mask)
        centroid.append(float(np.hypot(cols.mean() - centre[0], rows.mean() - centre[1])))
        radius.append(float(np.sqrt(n / np.pi) - label_radius))
    return {"centroid_px": np.array(centroid), "radius_px": np.array(radius), "area_px": np.array(area)}


def main(argv: list[str]) -> int:
    path = Path(argv[1]) if len(argv) > 1 else DEFAULT_DATA
    errors = press_errors(path)
    c, r = errors["centroid_px"], errors["radius_px"]
    print(f"{path}: {len(c)} presses, {MM_PER_PX} mm/px")
    print(f"centroid error  median {np.median(c):.2f} px ({np.median(c) * MM_PER_PX:.3f} mm), "
          f"90th pct {np.percentile(c, 90):.2f} px, max {c.max():.2f} px ({c.max() * MM_PER_PX:.3f} mm)")
    print(f"radius error    median {np.median(r):+.2f} px ({np.median(r) * MM_PER_PX:+.3f} mm), "
          f"median |.| {np.median(np.abs(r)):.2f} px ({np.median(np.abs(r)) * MM_PER_PX:.3f} mm), "
          f"range [{r.min():+.2f}, {r.max():+.2f}] px")
    area_mm2 = errors["area_px"] * MM_PER_PX**2
    print(f"contact area    median {np.median(area_mm2):.2f} mm^2 (labelled circles: "
          f"{np.pi * (17 * MM_PER_PX) ** 2:.2f} mm^2 at r = 17 px)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
