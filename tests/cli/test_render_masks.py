"""`mvtop render-masks`: files per frame and sensor, their sizes, and IoUs that match the masks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "sample_logs" / "conn1.mcap"
CONFIG = REPO / "configs" / "conn1.yaml"
SENSORS = {"front": (480, 640), "side": (480, 640), "left": (240, 320), "right": (240, 320)}


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, timeout=600)


def _mask(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127


def test_render_masks_with_a_track(tmp_path):
    track = tmp_path / "track"
    est = run(
        "estimate", str(SAMPLE), "--config", str(CONFIG), "--out", str(track), "--particles", "100", "--max-frames", "3"
    )
    assert est.returncode == 0, est.stderr
    out = tmp_path / "masks"
    proc = run(
        "render-masks", str(SAMPLE), "--config", str(CONFIG), "--track", str(track), "--frames", "0,2",
        "--out", str(out),
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "masks.json").read_text())
    assert [f["frame"] for f in summary["frames"]] == [0, 2]
    for fr in summary["frames"]:
        k = fr["frame"]
        for name, shape in SENSORS.items():
            base = out / f"frame_{k:04d}_{name}"
            for suffix in ("image", "observed", "estimate", "truth", "overlay"):
                img = cv2.imread(str(base.with_name(f"{base.name}_{suffix}.png")))
                assert img is not None and img.shape[:2] == shape, (k, name, suffix)
            observed, estimate, truth = (
                _mask(base.with_name(f"{base.name}_{s}.png")) for s in ("observed", "estimate", "truth")
            )
            for key, rendered in (("iou_estimate", estimate), ("iou_truth", truth)):
                expected = (observed & rendered).sum() / max(1, (observed | rendered).sum())
                assert abs(fr["sensors"][name][key] - expected) < 1e-9
            # the printed IoU is the one of the estimate
            assert f"{name} {fr['sensors'][name]['iou_estimate']:.3f}" in proc.stdout
        sheet = cv2.imread(str(out / f"frame_{k:04d}_sheet.png"))
        assert sheet.shape == (240, 4 * 320, 3)
    video = cv2.VideoCapture(str(out / "masks.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 2


def test_render_masks_at_ground_truth_and_at_a_given_pose(tmp_path):
    out = tmp_path / "gt"
    proc = run("render-masks", str(SAMPLE), "--config", str(CONFIG), "--frames", "5", "--no-video", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "masks.json").read_text())
    sensors = summary["frames"][0]["sensors"]
    assert sensors["left"]["iou_truth"] > 0.95 and sensors["right"]["iou_truth"] > 0.95  # depth vs truth
    assert not (out / "masks.mp4").exists()
    # a grasp pose 5 mm off shows at once in the tactile IoU
    bad = tmp_path / "bad"
    proc = run("render-masks", str(SAMPLE), "--config", str(CONFIG), "--frames", "5", "--no-video", "--out", str(bad),
               "--pose-ee", "0.005,0,0.0125,1,0,0,0")
    assert proc.returncode == 0, proc.stderr
    off = json.loads((bad / "masks.json").read_text())["frames"][0]["sensors"]
    assert off["left"]["iou_estimate"] < sensors["left"]["iou_truth"] - 0.05
    err = run("render-masks", str(SAMPLE), "--config", str(CONFIG), "--out", str(bad), "--pose-ee", "1,2,3")
    assert err.returncode == 2 and "--pose-ee" in err.stderr


def test_render_masks_uses_a_camera_as_the_run_corrected_it(tmp_path):
    """The sample with its front camera recorded turned 2 deg: `estimate` corrects the camera
    (summary.json's extrinsics), and `render-masks --track` renders through the camera as the run
    used it, so the ground truth's front mask is where the log as recorded puts it (IoU above
    0.95); without the track it is rendered through the turned camera, far from it."""
    turned = tmp_path / "turned.mcap"
    made = subprocess.run([sys.executable, str(REPO / "scripts" / "perturb_extrinsics.py"), str(SAMPLE), str(turned),
                           "front_optical", "2"], capture_output=True, text=True, timeout=600)
    assert made.returncode == 0, made.stderr
    track = tmp_path / "track"
    est = run("estimate", str(turned), "--config", str(CONFIG), "--out", str(track), "--particles", "50",
              "--max-frames", "1")
    assert est.returncode == 0, est.stderr
    assert "camera_extrinsics" in est.stderr and "camera 'front'" in est.stderr
    found = json.loads((track / "summary.json").read_text())["extrinsics"]
    assert found["front"]["corrected"] and not found["side"]["misaligned"]

    def truth_mask(log: Path, name: str, *extra: str) -> tuple[np.ndarray, dict]:
        out = tmp_path / name
        proc = run("render-masks", str(log), "--config", str(CONFIG), "--frames", "0", "--no-video",
                   "--out", str(out), *extra)
        assert proc.returncode == 0, proc.stderr
        return _mask(out / "frame_0000_front_truth.png"), json.loads((out / "masks.json").read_text())

    recorded, _ = truth_mask(SAMPLE, "recorded")
    corrected, summary = truth_mask(turned, "corrected", "--track", str(track))
    raw, raw_summary = truth_mask(turned, "raw")
    assert summary["cameras_turned_deg"]["front"][1] == pytest.approx(2.0, abs=0.1)
    assert raw_summary["cameras_turned_deg"] == {}
    assert (recorded & corrected).sum() / (recorded | corrected).sum() > 0.95
    assert (recorded & raw).sum() / (recorded | raw).sum() < 0.5
