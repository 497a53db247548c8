"""The public real data beside the checkout, ``../shared/data/real`` (its README says what each
folder checks: rosbag2 MCAP logs, GelSight presses with labelled contacts, the IndustReal peg's
CAD). Tests that read it carry ``needs_real_data``: in a clone without that folder they are
skipped, the reason naming the folder, and every other test still runs."""

from pathlib import Path

import pytest

REAL_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"

needs_real_data = pytest.mark.skipif(
    not REAL_DATA.is_dir(), reason=f"reads the public real data in {REAL_DATA}, which is not beside this checkout"
)
