"""inspect_log / format_report: topics and rates of a log, and what a config needs but the log lacks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _real_data import REAL_DATA, needs_real_data

from mvtop_cli.errors import LogError
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.io.mcap_writer import LogWriter
from mvtop_cli.pipelines.inspect import format_report, inspect_log

REAL = REAL_DATA / "rosbag2_mcap"
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


@pytest.fixture(scope="module")
def log_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("inspect") / "run.mcap"
    cam = PinholeCamera.from_fov(8, 6, 10.0)
    with LogWriter(path) as w:
        w.write_tf([("world", "front_optical", np.eye(4))], T0, static=True)
        for i in range(51):  # 50 Hz for 1 s
            t = T0 + i * 20 * MS
            w.write_tf([("world", "ee", np.eye(4))], t)
            w.write_bool("/contact", i > 25, t)
        for i in range(11):  # 10 Hz
            t = T0 + i * 100 * MS
            w.write_image("/cameras/front/image", np.zeros((6, 8, 3), np.uint8), t, "front_optical")
            w.write_camera_info("/cameras/front/camera_info", cam, t, "front_optical")
    return path


REQUIRED = {
    "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/cameras/front/image": "sensor_msgs/msg/Image",
    "/cameras/front/camera_info": "sensor_msgs/msg/CameraInfo",
    "/contact": "std_msgs/msg/Bool",
}


def test_complete_log_passes(log_path):
    report = inspect_log(log_path, REQUIRED, ["world", "ee", "front_optical"])
    assert report.ok
    s = report.summary
    assert {t.name: t.message_count for t in s.topics} == {
        "/tf_static": 1, "/tf": 51, "/contact": 51, "/cameras/front/image": 11, "/cameras/front/camera_info": 11,
    }
    assert s.topic("/tf").rate_hz == pytest.approx(50.0)
    assert s.topic("/cameras/front/image").rate_hz == pytest.approx(10.0)
    assert s.duration_s == pytest.approx(1.0) and s.time_range_ns == (T0, T0 + 1000 * MS)
    assert report.tf_frames == ("ee", "front_optical", "world")
    text = format_report(report)
    assert "OK: every required topic and TF frame is present." in text
    assert "duration:    1.000 s" in text and "start:       2023-11-14 22:13:20.000000000 UTC" in text
    lines = text.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("topic "))
    assert lines[header].split() == ["topic", "type", "count", "rate", "Hz", "span", "s", "check"]
    tf_row = next(line for line in lines if line.startswith("/tf "))
    assert tf_row.split() == ["/tf", "tf2_msgs/msg/TFMessage", "51", "50.00", "1.000", "required"]
    # columns line up: every table row is as wide as its separator line or narrower
    assert len(lines[header + 1]) >= max(len(line) for line in lines[header + 2 : header + 7])


def test_missing_wrong_and_empty_topics_and_frames(log_path):
    required = dict(REQUIRED)
    required["/tactile/left/image"] = "sensor_msgs/msg/Image"
    required["/contact"] = "sensor_msgs/msg/JointState"
    report = inspect_log(log_path, required, ["world", "ee", "tactile_left_optical"])
    assert not report.ok
    assert report.missing_topics == ("/tactile/left/image",)
    assert report.wrong_types == (("/contact", "sensor_msgs/msg/JointState", "std_msgs/msg/Bool"),)
    assert report.missing_frames == ("tactile_left_optical",)
    text = format_report(report)
    assert "PROBLEMS:" in text
    assert "  - missing topics: /tactile/left/image" in text
    assert "  - wrong types: /contact is std_msgs/msg/Bool (expected sensor_msgs/msg/JointState)" in text
    assert "  - missing TF frames: tactile_left_optical" in text
    assert any(line.startswith("/tactile/left/image") and line.endswith("MISSING") for line in text.splitlines())


def test_without_requirements_tf_is_not_scanned(log_path):
    report = inspect_log(log_path)
    assert report.ok and report.tf_frames is None
    assert "PROBLEMS" not in format_report(report) and "TF frames" not in format_report(report)
    assert inspect_log(log_path, scan_tf=True).tf_frames == ("ee", "front_optical", "world")


@needs_real_data
def test_real_bag_with_empty_channels():
    folder = REAL / "rosbag2_py_test_resources_mcap_talker"
    report = inspect_log(
        folder, {"/parameter_events": "rcl_interfaces/msg/ParameterEvent", "/topic": "std_msgs/String"}
    )
    assert report.empty_topics == ("/parameter_events",) and not report.missing_topics and not report.wrong_types
    text = format_report(report)
    assert "files:       1 (talker.mcap)" in text and "compression: zstd" in text
    assert "  - topics without messages: /parameter_events" in text
    row = next(line for line in text.splitlines() if line.startswith("/parameter_events"))
    assert row.split()[2:5] == ["0", "-", "-"] and row.endswith("EMPTY")


def test_truncated_log_is_flagged_not_rejected(log_path, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log_path.read_bytes()[: log_path.stat().st_size // 2])
    report = inspect_log(cut, {"/tf": "tf2_msgs/msg/TFMessage"})
    assert not report.ok and report.summary.truncated_at is not None
    text = format_report(report)
    assert "WARNING:     cut.mcap is truncated at byte" in text and "  - the log is truncated" in text


def test_unreadable_log_raises(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not mcap at all")
    with pytest.raises(LogError, match=r"x\.mcap: not an MCAP file"):
        inspect_log(bad)


def test_inspect_reports_dropped_frames_and_rate_mismatch(tmp_path):
    import numpy as np

    from mvtop_cli.io.mcap_writer import LogWriter
    from mvtop_cli.pipelines.inspect import format_report, inspect_log

    path = tmp_path / "rates.mcap"
    t0, ms = 1_700_000_000_000_000_000, 1_000_000
    img = np.zeros((4, 6, 3), np.uint8)
    with LogWriter(path) as w:
        for k in range(20):  # front: 10 Hz, frames 7 and 8 dropped
            if k not in (7, 8):
                w.write_image("/cameras/front/image", img, t0 + k * 100 * ms, "front_optical")
        for k in range(10):  # side: 5 Hz
            w.write_image("/cameras/side/image", img, t0 + k * 200 * ms, "side_optical")
    need = {"/cameras/front/image": "sensor_msgs/msg/Image", "/cameras/side/image": "sensor_msgs/msg/Image"}
    report = inspect_log(path, need)
    front, side = report.timing["/cameras/front/image"], report.timing["/cameras/side/image"]
    assert front["dropped"] == 2 and abs(front["max_gap_s"] - 0.3) < 1e-9 and abs(front["rate_hz"] - 10) < 1e-6
    assert side["dropped"] == 0 and side["rate_mismatch"] and not front["rate_mismatch"]
    text = format_report(report)
    assert "2 dropped (gap up to 0.300 s)" in text and "slower than the fastest sensor" in text


def gt_log(path: Path, gt_frame: str) -> Path:
    """A log with world -> ee on /tf, world -> front_optical on /tf_static, a camera, contact
    and ground truth on /gt in ``gt_frame``."""
    cam = PinholeCamera.from_fov(8, 6, 10.0)
    with LogWriter(path) as w:
        w.write_tf([("world", "front_optical", np.eye(4))], T0, static=True)
        for i in range(3):
            t = T0 + i * 100 * MS
            w.write_tf([("world", "ee", np.eye(4))], t)
            w.write_bool("/contact", False, t)
            w.write_image("/cameras/front/image", np.zeros((6, 8, 3), np.uint8), t, "front_optical")
            w.write_camera_info("/cameras/front/camera_info", cam, t, "front_optical")
            w.write_pose("/gt", np.eye(4), t, gt_frame)
    return path


@pytest.mark.parametrize("frame", ["world", "ee", "front_optical"])
def test_ground_truth_in_a_frame_tf_connects_passes(tmp_path, frame):
    report = inspect_log(gt_log(tmp_path / "gt.mcap", frame), REQUIRED, ["world", "ee"], ground_truth_topic="/gt")
    assert report.ok and report.ground_truth.frame == frame and report.ground_truth.connected
    text = format_report(report)
    note = "" if frame == "world" else " (converted through TF)"
    assert f"ground truth: /gt in frame {frame!r}{note}" in text.splitlines()
    assert "OK: every required topic and TF frame is present. The ground truth's frame connects to the world." in text


def test_ground_truth_in_a_frame_tf_does_not_connect_is_a_problem(tmp_path):
    path = gt_log(tmp_path / "gt.mcap", "tray")
    report = inspect_log(path, REQUIRED, ["world", "ee"], ground_truth_topic="/gt")
    assert not report.ok and not report.ground_truth.connected
    text = format_report(report)
    assert "ground truth: /gt in frame 'tray' (NOT CONNECTED to 'world' through TF)" in text.splitlines()
    assert ("  - ground truth on /gt is in frame 'tray', which TF does not connect to 'world' (expected its poses "
            "in 'world', or a frame on a TF chain to it)") in text.splitlines()
    # without requirements TF is scanned only for the ground truth; a missing topic is no problem here
    assert not inspect_log(path, ground_truth_topic="/gt").ground_truth.connected
    assert inspect_log(path, ground_truth_topic="/missing").ground_truth is None
