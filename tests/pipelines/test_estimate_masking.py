"""Masking choices of the config reach the estimator: the promptable mode switches on once the
belief has converged, and only when the config asks for it."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]


def _modes(out: Path) -> list[str]:
    with (out / "track.csv").open() as fh:
        return [row["mask_mode"] for row in csv.DictReader(fh)]


def test_prompt_mode_only_when_configured_and_converged(tmp_path):
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    opts = EstimateOptions(modalities=("vision", "tactile"), num_particles=150, max_frames=8)
    estimate(ROOT / "sample_logs" / "conn2.mcap", cfg, tmp_path / "off", opts)
    assert set(_modes(tmp_path / "off")) == {"proposals"}
    on = replace(cfg, masking=replace(cfg.masking, prompt_when_converged=True))
    summary = estimate(ROOT / "sample_logs" / "conn2.mcap", on, tmp_path / "on", opts)
    modes = _modes(tmp_path / "on")
    assert modes[0] == "proposals" and "prompt" in modes  # the first frame is never converged
    assert summary["frames_processed"] == 8
