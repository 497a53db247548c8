"""End-to-end checks of ``mvtop estimate`` on the simulated sample logs (ground truth on
/ground_truth/object_pose): accuracy of the final frame, determinism, and the output files."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate, log_topics, sensor_topics

ROOT = Path(__file__).resolve().parents[2]
OBJECTS = ("cube", "shaft_peg", "plug", "conn1", "conn2")
TRACK_COLUMNS = [
    "frame", "stamp_ns", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw",
    "ee_x_m", "ee_y_m", "ee_z_m", "ee_qx", "ee_qy", "ee_qz", "ee_qw",
    "std_translation_m", "std_rotation_deg", "ess", "contact",
    "evidence_min_iou", "evidence_sigma_translation_m", "evidence_sigma_rotation_deg", "mask_mode", "flags",
]
SUMMARY_KEYS = {"log", "object", "modalities", "particles", "seed", "frames_processed", "frames_skipped",
                "run_time_s", "time_per_frame_s", "final", "flags", "evidence"}


def paths(name: str) -> tuple[Path, Path]:
    return ROOT / "sample_logs" / f"{name}.mcap", ROOT / "configs" / f"{name}.yaml"


def ground_truth_at(log_path: Path, cfg, stamp_ns: int) -> np.ndarray:
    """T_world_object of the ground truth at the frame with ``stamp_ns``."""
    with McapLog(log_path) as log:
        for frame in FrameReader(log, sensor_topics(cfg), log_topics(cfg)):
            if frame.stamp_ns == stamp_ns:
                assert frame.T_world_object_gt is not None
                return frame.T_world_object_gt
    raise AssertionError(f"no frame at {stamp_ns} in {log_path}")


def symmetric_error(T_est: np.ndarray, T_gt: np.ndarray, symmetries) -> tuple[float, float]:
    """(translation [mm], rotation [deg]) of the symmetric equivalent ``T_est @ S`` closest
    in rotation to the truth (S over the identity and the config's symmetries)."""
    best = None
    for S in [np.eye(4)] + [s.matrix() for s in symmetries]:
        T = T_est @ S
        rot = float(np.degrees(se3.rotation_angle(T[:3, :3], T_gt[:3, :3])))
        trans = float(1000 * np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))
        if best is None or rot < best[1]:
            best = (trans, rot)
    return best


def final_pose(summary: dict) -> np.ndarray:
    f = summary["final"]["T_world_object"]
    return se3.from_quat_xyzw(np.asarray(f["quaternion_xyzw"]), np.asarray(f["translation_m"]))


def test_symmetric_error_takes_the_closest_equivalent():
    cfg = load_config(paths("cube")[1])
    T_gt = cfg.grasp_prior.pose.matrix()
    S = cfg.object.symmetries[2].matrix()  # 180 deg about the object z axis
    trans, rot = symmetric_error(T_gt @ np.linalg.inv(S), T_gt, cfg.object.symmetries)
    assert trans == pytest.approx(0.0, abs=1e-6) and rot == pytest.approx(0.0, abs=1e-4)
    moved = T_gt.copy()
    moved[0, 3] += 0.002
    trans, rot = symmetric_error(moved, T_gt, cfg.object.symmetries)
    assert trans == pytest.approx(2.0, abs=1e-6) and rot == pytest.approx(0.0, abs=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECTS)
def test_final_frame_within_1mm_and_1deg(name, tmp_path):
    """Vision + tactile + contact, default particle count and seed: the last frame of each
    30-frame sample log is within 1 mm and 1 degree of the ground truth (modulo the object's
    symmetries)."""
    log_path, cfg_path = paths(name)
    cfg = load_config(cfg_path)
    t0 = time.perf_counter()
    summary = estimate(log_path, cfg, tmp_path / "out")
    elapsed = time.perf_counter() - t0
    assert summary["modalities"] == ["vision", "tactile", "contact"]
    assert summary["frames_processed"] == 30
    T_gt = ground_truth_at(log_path, cfg, summary["final"]["stamp_ns"])
    trans, rot = symmetric_error(final_pose(summary), T_gt, cfg.object.symmetries)
    print(f"{name}: final error {trans:.3f} mm {rot:.3f} deg in {elapsed:.1f} s")
    assert trans < 1.0, f"{name}: final translation error {trans:.3f} mm"
    assert rot < 1.0, f"{name}: final rotation error {rot:.3f} deg"
    # the evidence pins every axis in every frame of these clean logs: no suspect_estimate
    assert "suspect_estimate" not in summary["warning_counts"]


def _short_run(out: Path, seed: int = 3) -> dict:
    """Three frames, few particles; without the contact modality, whose signed-distance
    field takes longer to build than these frames take to filter."""
    log_path, cfg_path = paths("conn2")
    return estimate(log_path, load_config(cfg_path), out,
                    EstimateOptions(modalities=("vision", "tactile"), num_particles=120, seed=seed, max_frames=3))


def test_same_seed_gives_identical_track(tmp_path):
    _short_run(tmp_path / "a")
    _short_run(tmp_path / "b")
    _short_run(tmp_path / "c", seed=4)
    a, b, c = ((tmp_path / d / "track.csv").read_text() for d in "abc")
    assert a == b
    assert a != c  # the seed does reach the filter


def test_output_files_and_columns(tmp_path):
    out = tmp_path / "out"
    summary = _short_run(out)
    for name in ("track.mcap", "track.csv", "summary.json", "config.resolved.yaml"):
        assert (out / name).is_file(), name
    with open(out / "track.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == TRACK_COLUMNS
    assert len(rows) == 1 + 3
    for row in rows[1:]:
        assert len(row) == len(TRACK_COLUMNS)
        q = np.array([float(v) for v in row[5:9]])
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-6)
        assert row[19] == "0"  # the log's contact signal (free air here), read though contact is not a modality
        assert row[23] in ("proposals", "prompt")
        assert float(row[16]) >= 0 and float(row[18]) > 0
        # the evidence diagnostic: every sensor explained (IoU in (0, 1]) and a likelihood that
        # pins the pose to within a few millimetres / degrees around the estimate
        assert 0.5 < float(row[20]) <= 1.0
        assert 0 < float(row[21]) < 0.005 and 0 < float(row[22]) < 5.0
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == summary
    assert SUMMARY_KEYS <= set(summary)
    assert summary["particles"] == 120 and summary["frames_processed"] == 3
    final = summary["final"]
    assert np.isfinite(final["ground_truth_translation_error_mm"])
    assert np.isfinite(final["ground_truth_rotation_error_deg"])
    assert np.asarray(final["covariance_ee"]).shape == (6, 6)
    ev = summary["evidence"]
    assert [r[0] for r in ev["per_frame"]["rows"]] == [0, 1, 2]
    assert ev["final"]["min_iou"] == pytest.approx(float(rows[-1][20]), abs=1e-4)
    assert ev["final"]["min_iou"] == pytest.approx(min(ev["final"]["sensor_iou"].values()))
    assert max(ev["final"]["likelihood_sigma_translation_m"]) == pytest.approx(float(rows[-1][21]), abs=1e-9)
    # the track's last row is the summary's final pose
    last = rows[-1]
    assert np.allclose([float(v) for v in last[2:5]], final["T_world_object"]["translation_m"], atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("modality", ["vision", "tactile"])
def test_single_modality_runs_complete(modality, tmp_path):
    """Vision only and tactile only run through a whole log (numbers printed, not asserted:
    one modality alone is not expected to reach the 1 mm / 1 degree target)."""
    log_path, cfg_path = paths("cube")
    cfg = load_config(cfg_path)
    summary = estimate(log_path, cfg, tmp_path / "out", EstimateOptions(modalities=(modality,)))
    assert summary["modalities"] == [modality]
    assert summary["frames_processed"] == 30
    T_gt = ground_truth_at(log_path, cfg, summary["final"]["stamp_ns"])
    trans, rot = symmetric_error(final_pose(summary), T_gt, cfg.object.symmetries)
    print(f"cube {modality} only: final error {trans:.3f} mm {rot:.3f} deg in {summary['run_time_s']:.1f} s")
    assert np.isfinite(trans) and np.isfinite(rot)
    with open(tmp_path / "out" / "track.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert len(rows) == 31
    # the log's contact signal, read though contact is not a modality of this run (it sets the
    # motion noise): free air first, then the receptacle
    contact = [r[19] for r in rows[1:]]
    assert contact[0] == "0" and contact[-1] == "1" and set(contact) == {"0", "1"}
