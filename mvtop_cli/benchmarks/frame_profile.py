"""Where one `mvtop estimate` run spends its time, per stage and frame (``benchmark speed --log``)."""

from __future__ import annotations

import tempfile
from pathlib import Path

from ..config import Config
from ..pipelines.estimate import EstimateOptions, estimate


def profile_estimate(log_path: Path, cfg: Config, max_frames: int | None = None) -> dict:
    """Run the estimate over ``log_path`` (the first ``max_frames`` frames) into a temporary
    folder and return its ``summary.json`` timing block (``pipelines.track.stage_timing``)
    with the run time and frames processed."""
    with tempfile.TemporaryDirectory(prefix="mvtop-speed-") as tmp:
        summary = estimate(log_path, cfg, Path(tmp) / "out", EstimateOptions(max_frames=max_frames))
    return {"run_time_s": summary["run_time_s"], "frames_processed": summary["frames_processed"],
            **summary["timing"]}
