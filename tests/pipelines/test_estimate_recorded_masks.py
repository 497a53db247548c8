"""End to end: a log whose cameras come with object masks recorded by a segmenter
(``mvtop simulate --mask-topics``) is estimated with ``masking.camera.backend: topic``."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def run(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, timeout=900,
                          cwd=REPO, env=env)


@pytest.fixture(scope="module")
def masked_log(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("masks")
    proc = run("simulate", "--object", "cube", "--seed", "5", "--frames", "12", "--mask-topics", "raw",
               "--out", str(d / "log.mcap"), "--write-config", str(d / "config.yaml"))
    assert proc.returncode == 0, proc.stderr
    return d / "log.mcap", d / "config.yaml"


@pytest.mark.slow
def test_recorded_masks_estimate_within_the_sample_log_tolerance(masked_log, tmp_path):
    """Vision + touch + contact with the recorded masks as the camera masks: the final frame
    within 1 mm and 1 deg of the truth (the sample logs' tolerance); every frame used them."""
    log, cfg = masked_log
    proc = run("estimate", str(log), "--config", str(cfg), "--out", str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    final = summary["final"]
    assert final["ground_truth_translation_error_mm"] < 1.0, final
    assert final["ground_truth_rotation_error_deg"] < 1.0, final
    with open(tmp_path / "out" / "track.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 12 and all(r["mask_mode"] == "recorded" for r in rows)


def test_inspect_lists_the_mask_topics_as_required(masked_log):
    log, cfg = masked_log
    proc = run("inspect", str(log), "--config", str(cfg))
    assert proc.returncode == 0, proc.stderr
    topics = [ln.split() for ln in proc.stdout.splitlines() if ln.startswith("/cameras/") and "/mask" in ln]
    listed = {t[0]: t for t in topics if len(t) > 2 and t[1].startswith("sensor_msgs/")}  # the topic table
    assert sorted(listed) == ["/cameras/front/mask", "/cameras/side/mask"]
    assert all(t[1] == "sensor_msgs/msg/Image" and t[-1] == "required" for t in listed.values())


def test_a_missing_mask_topic_is_one_error_line(masked_log, tmp_path):
    log, cfg = masked_log
    data = yaml.safe_load(cfg.read_text())
    data["sensors"]["cameras"][1]["mask_topic"] = "/cameras/side/masks"
    data["object"]["mesh"] = str(cfg.parent / data["object"]["mesh"])
    for env in data["environment"]:
        env["mesh"] = str(cfg.parent / env["mesh"])
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    proc = run("estimate", str(log), "--config", str(bad), "--out", str(tmp_path / "out"))
    assert proc.returncode != 0
    err = proc.stderr.strip()
    assert err.count("\n") == 0, err
    assert f"{log}: topic '/cameras/side/masks' not found (expected sensor_msgs/msg/Image or " \
           "sensor_msgs/msg/CompressedImage for the object masks of 'side')" in err
    assert not (tmp_path / "out").exists()
