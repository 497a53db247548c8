"""summary.json from a run's frame estimates (``pipelines.track.run_summary``): the run-level
``suspect_estimate`` warning follows the frames whose evidence leaves a pose axis open."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.estimator.estimator import FrameEstimate
from mvtop_cli.estimator.evidence import EvidenceReport
from mvtop_cli.pipelines.track import run_summary, warning_report

ROOT = Path(__file__).resolve().parents[2]


def _frames(open_axes: list[bool]) -> list[FrameEstimate]:
    """Frame estimates at the identity whose evidence leaves the z rotation open where asked."""
    out = []
    for i, is_open in enumerate(open_axes):
        sigma = np.array([1e-4, 1e-4, 1e-4, 0.01, 0.01, np.inf if is_open else 0.01])
        out.append(FrameEstimate(
            index=i, stamp_ns=1_000_000_000 + i * 100_000_000, T_ee_object=np.eye(4), T_world_object=np.eye(4),
            covariance=np.eye(6) * 1e-8, ess=100.0, contact=False, sensors=("front",), flags=(),
            mask_mode="proposals", particles_world=np.eye(4)[None],
            evidence=EvidenceReport({"front": 0.95}, 10.0, sigma)))
    return out


def test_suspect_estimate_is_a_run_warning_when_enough_frames_leave_an_axis_open(tmp_path: Path):
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    assert cfg.output.suspect_unpinned_fraction == 0.4
    frames = _frames([False, True, False, True, False])  # 2 of 5 open: 40 %
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    suspect = [w for w in summary["warnings"] if w["kind"] == "suspect_estimate"]
    assert len(suspect) == 1 and suspect[0]["frame"] is None
    assert suspect[0]["unpinned_frames"] == 2 and suspect[0]["frames"] == 5
    assert summary["warning_counts"]["suspect_estimate"] == 1
    assert any(line.startswith("suspect_estimate: the evidence left some pose axis open in 2 of 5 frames")
               for line in warning_report(summary))
    # the threshold is the config's: above the run's fraction, or null, no warning
    for value in (0.5, None):
        other = replace(cfg, output=replace(cfg.output, suspect_unpinned_fraction=value))
        assert "suspect_estimate" not in run_summary(frames, other, tmp_path / "log.mcap", 1.0, [])["warning_counts"]
    # frames without evidence do not count
    quiet = _frames([False] * 5) + [replace(f, evidence=None) for f in _frames([True] * 5)]
    assert "suspect_estimate" not in run_summary(quiet, cfg, tmp_path / "log.mcap", 1.0, [])["warning_counts"]
