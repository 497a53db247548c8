"""summary.json from a run's frame estimates (``pipelines.track.run_summary``): the run-level
``suspect_estimate`` warning follows the frames that leave the pose open (an axis the evidence
does not pin, or a rival mode standing)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.estimator.estimator import FrameEstimate
from mvtop_cli.estimator.evidence import EvidenceReport
from mvtop_cli.filter.health import RivalMode
from mvtop_cli.pipelines.track import closed_frames, pinned_frames, run_summary, warning_report

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
    assert summary["suspect"] == {"raised": True, "causes": ["unpinned"], "unpinned_frames": 2, "evidence_frames": 5,
                                  "unpinned_threshold": 0.4}
    assert any(line.startswith("suspect_estimate: the evidence left some pose axis or a rival mode open in 2 of 5 "
                               "frames")
               for line in warning_report(summary))
    # the threshold is the config's: above the run's fraction, or null, no warning
    for value in (0.5, None):
        other = replace(cfg, output=replace(cfg.output, suspect_unpinned_fraction=value))
        quiet = run_summary(frames, other, tmp_path / "log.mcap", 1.0, [])
        assert "suspect_estimate" not in quiet["warning_counts"]
        # what would raise it is kept all the same: the share of open frames and the threshold it missed
        assert quiet["suspect"] == {"raised": False, "causes": [], "unpinned_frames": 2, "evidence_frames": 5,
                                    "unpinned_threshold": value}
    # frames without evidence do not count
    quiet = _frames([False] * 5) + [replace(f, evidence=None) for f in _frames([True] * 5)]
    assert "suspect_estimate" not in run_summary(quiet, cfg, tmp_path / "log.mcap", 1.0, [])["warning_counts"]


def test_suspect_keeps_every_cause_that_holds_at_the_end(tmp_path: Path):
    """A rival mode and a sensor disagreement still standing at the last frame, with too many open
    frames: the record's sentence names the open frames, and ``suspect`` lists all three causes."""
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    frames = _frames([True, True, False])
    rival = RivalMode(frame=1, translation_mm=2.5, rotation_deg=1.0, nats_below=1.5)
    dissent = RivalMode(frame=0, translation_mm=4.0, rotation_deg=6.0, nats_below=-9.0, sensor="front",
                        others_gain=12.0)
    frames[-1] = replace(frames[-1], rival=rival, disagreement=dissent)
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    assert summary["suspect"]["causes"] == ["unpinned", "rival_mode", "sensors_disagree"]
    (record,) = [w for w in summary["warnings"] if w["kind"] == "suspect_estimate"]
    assert record["unpinned_frames"] == 3  # two open axes, and the last frame's rival
    # without the open frames the rival names the record; the disagreement is still kept as a cause
    frames = [replace(f, evidence=EvidenceReport({"front": 0.95}, 10.0, np.full(6, 0.01))) for f in frames]
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    assert summary["suspect"] == {"raised": True, "causes": ["rival_mode", "sensors_disagree"], "unpinned_frames": 1,
                                  "evidence_frames": 3, "unpinned_threshold": 0.4}
    (record,) = [w for w in summary["warnings"] if w["kind"] == "suspect_estimate"]
    assert record["rival_frame"] == 1 and record["rival_translation_mm"] == 2.5


def test_frames_a_rival_stood_on_count_as_open(tmp_path: Path):
    """A rival mode that stood over frames 1-3 and was ruled out at the last frame: every axis pinned
    on every frame, so only the rival's frames leave the pose open, 3 of 5 (60 %): the run is
    suspect by the share although no rival stands at its end (a wrong mode a check, scoring on the
    masks the belief chose, ruled out late). summary.json's per-frame ``rival`` column holds them."""
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    rival = RivalMode(frame=1, translation_mm=1.65, rotation_deg=13.9, nats_below=-13.3)
    frames = [replace(f, rival=rival if 1 <= i <= 3 else None) for i, f in enumerate(_frames([False] * 5))]
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    assert summary["suspect"] == {"raised": True, "causes": ["unpinned"], "unpinned_frames": 3, "evidence_frames": 5,
                                  "unpinned_threshold": 0.4}
    (record,) = [w for w in summary["warnings"] if w["kind"] == "suspect_estimate"]
    assert record["unpinned_frames"] == 3 and record["unpinned_fraction"] == 0.6
    assert [r[-1] for r in summary["evidence"]["per_frame"]["rows"]] == [False, True, True, True, False]
    assert pinned_frames(summary["evidence"]) == [True] * 5
    assert closed_frames(summary["evidence"]) == [True, False, False, False, True]
    # one frame of five with a rival: 20 %, below the threshold, and none at the end: no record
    frames = [replace(f, rival=rival if i == 1 else None) for i, f in enumerate(_frames([False] * 5))]
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    assert summary["suspect"]["raised"] is False and summary["suspect"]["unpinned_frames"] == 1
    assert "suspect_estimate" not in summary["warning_counts"]


def test_an_axis_the_profile_leaves_open_counts_as_open(tmp_path: Path):
    """Touch alone: the one-axis probe pins every axis, but the profile (measured on a check frame and
    kept until the next) finds a pose as good as the estimate along x. Those frames count as open,
    in summary.json's per-frame ``pinned`` column and towards the ``suspect_estimate`` warning."""
    cfg = load_config(ROOT / "configs" / "conn1.yaml")
    profile = np.array([np.inf, 8e-5, 2e-4, 0.004, 0.03, 0.003])
    frames = [replace(f, evidence=replace(f.evidence, profile_sigma=profile if i >= 2 else None))
              for i, f in enumerate(_frames([False] * 5))]
    summary = run_summary(frames, cfg, tmp_path / "log.mcap", 1.0, [])
    per_frame = summary["evidence"]["per_frame"]
    assert per_frame["columns"][-2:] == ["pinned", "rival"]
    assert [r[-2:] for r in per_frame["rows"]] == [[True, False], [True, False], [False, False], [False, False],
                                                   [False, False]]
    # the probe's own widths stay as they were: every axis within its step
    assert all(r[2] is not None and r[3] is not None for r in per_frame["rows"])
    assert pinned_frames(summary["evidence"]) == [True, True, False, False, False]
    assert pinned_frames(summary["evidence"], probe_only=True) == [True] * 5  # the rule before the profile counted
    assert summary["suspect"] == {"raised": True, "causes": ["unpinned"], "unpinned_frames": 3, "evidence_frames": 5,
                                  "unpinned_threshold": 0.4}
    # a profile that finds nothing as good within its reach pins the axis
    pinned = [replace(f, evidence=replace(f.evidence, profile_sigma=np.where(np.isinf(profile), 1e-3, profile)))
              for f in frames]
    summary = run_summary(pinned, cfg, tmp_path / "log.mcap", 1.0, [])
    assert "suspect_estimate" not in summary["warning_counts"]
    assert pinned_frames(summary["evidence"]) == [True] * 5


def test_pinned_frames_of_a_folder_written_before_the_column():
    """Older summary.json files have no ``pinned`` column: a null probe width marks an open frame."""
    evidence = {"per_frame": {"columns": ["frame", "min_iou", "sigma_translation_m", "sigma_rotation_deg"],
                              "rows": [[0, 0.9, 1e-4, 0.2], [1, 0.9, None, 0.2], [2, 0.9, 1e-4, None]]}}
    assert pinned_frames(evidence) == [True, False, False]
    # nor a ``rival`` column: the frames track.csv flags rival_mode are given
    assert closed_frames(evidence, {0}) == [False, False, False]
    assert closed_frames(evidence) == [True, False, False]
