"""Where the contact model's signed-distance grid lies and how fine it is.

The grid covers the receptacle-sized world-fixed parts (under 10 cm: receptacles, fixtures;
not the board or table they stand on, whose top face inside the box is still in the grid)
with a 5 mm margin: contact happens there; farther out phi is only needed to be large, and
the grid's continuation beyond its box (value + distance) gives that. The grid holds at most
``max_cells`` cells (2e7: ~80 MB of float32, a few seconds to build). When the box needs more
cells at the configured resolution (a receptacle with a wide flange), the box is first cut
laterally to the window the object can reach around the smallest part (the receptacle's
mouth): half its size and twice the margin either side of that part's centre. Only if that is still
too large does the resolution coarsen, and a grid coarser than the part's clearance is
reported (both numbers), since contact then cannot resolve the fit.
"""

from __future__ import annotations

import numpy as np

SMALL_PART_M = 0.1  # parts under this size bound the grid
MARGIN_M = 0.005
MAX_CELLS = 2e7


def contact_grid(boxes: list[np.ndarray], object_extent_m: float, resolution_m: float, clearance_m: float,
                 max_cells: float = MAX_CELLS) -> tuple[np.ndarray, float, str | None]:
    """``(bounds (2, 3) [m], resolution [m], warning or None)`` of the grid over the world-fixed
    parts whose world bounding boxes are ``boxes`` (each (2, 3)), for an object
    ``object_extent_m`` across with per-side ``clearance_m``."""
    boxes = [np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in boxes]
    small = [b for b in boxes if np.max(b.max(axis=0) - b.min(axis=0)) < SMALL_PART_M] or boxes
    lo = np.min([b.min(axis=0) for b in small], axis=0) - MARGIN_M
    hi = np.max([b.max(axis=0) for b in small], axis=0) + MARGIN_M

    def cells(lo_: np.ndarray, hi_: np.ndarray, res: float) -> float:
        return float(np.prod((hi_ - lo_) / res))

    note = None
    if cells(lo, hi, resolution_m) > max_cells:
        target = min(boxes, key=lambda b: float(np.max(b.max(axis=0) - b.min(axis=0))))
        centre = (target.min(axis=0) + target.max(axis=0)) / 2.0
        half = 0.5 * object_extent_m + 2 * MARGIN_M  # the object held over the mouth reaches this far
        lo[:2] = np.maximum(lo[:2], centre[:2] - half)
        hi[:2] = np.minimum(hi[:2], centre[:2] + half)
        note = (f"the contact grid covers {1e3 * (hi[0] - lo[0]):.0f} x {1e3 * (hi[1] - lo[1]):.0f} mm around the "
                "receptacle's centre, where the object can touch it")
    res = resolution_m
    if cells(lo, hi, res) > max_cells:
        res = float((np.prod(hi - lo) / max_cells) ** (1 / 3))
    if res > clearance_m:
        warning = (f"contact grid cells are {1e3 * res:.3g} mm, coarser than the part's clearance of "
                   f"{1e3 * clearance_m:.3g} mm (contact.sdf_resolution_m {resolution_m:g} m"
                   + (f"; the {1e3 * (hi - lo).max():.0f} mm box needs more than {max_cells:.0e} cells at it"
                      if res > resolution_m else "") + "): the contact model cannot resolve the fit; "
                   "set contact.sdf_resolution_m below the clearance or make the fixed parts smaller")
        return np.stack([lo, hi]), res, warning if note is None else f"{warning} ({note})"
    return np.stack([lo, hi]), res, None
