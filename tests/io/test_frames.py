"""Frames from a synthetic log with known motion: grouping, poses, images, contact, fingers, ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from _io_scene import (
    CAMERA,
    MISSING,
    MS,
    N_FRAMES,
    OFFSETS,
    T0,
    TACTILE,
    depth_of,
    image_of,
    trigger,
    write_scene,
)

from mvtop_cli.errors import LogError
from mvtop_cli.io.frames import FrameReader, LogTopics, SensorTopics, iter_frames, undistort_maps
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter

SENSORS = [
    SensorTopics.default("front", "camera"),
    SensorTopics.default("side", "camera", compressed=True),
    SensorTopics.default("left", "tactile", depth=True),
    SensorTopics.default("right", "tactile"),
]
TOPICS = LogTopics(sync_tolerance_ns=5 * MS)


def read_frames(path, **kw):
    with McapLog(path) as log:
        reader = FrameReader(log, SENSORS, TOPICS, **kw)
        frames = list(reader)
    return frames, reader


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_frames_match_the_known_scene(tmp_path, compression):
    path = tmp_path / f"scene_{compression}.mcap"
    sc = write_scene(path, compression)
    frames, reader = read_frames(path)

    assert [f.index for f in frames] == list(range(N_FRAMES))
    # The image before the first /tf sample is skipped and reported, not fatal.
    assert len(reader.skipped) == 1 and reader.skipped[0][0] == T0 - 30 * MS
    assert "no TF for world -> ee" in reader.skipped[0][1]

    for k, f in enumerate(frames):
        present = [n for n in OFFSETS if (n, k) not in MISSING]
        assert f.stamp_ns == trigger(k) + min(OFFSETS[n] for n in present)  # earliest stamp
        assert set(f.cameras) == {n for n in ("front", "side") if n in present}
        assert set(f.tactile) == {"left", "right"}
        np.testing.assert_allclose(f.T_world_ee, sc.T_world_ee(f.stamp_ns), atol=1e-12)
        for name, img in {**f.cameras, **f.tactile}.items():
            st = trigger(k) + OFFSETS[name]
            assert img.stamp_ns == st
            # the end effector at the image's own time (the sensors are 1-3 ms apart)
            np.testing.assert_allclose(img.T_world_ee, sc.T_world_ee(st), atol=1e-12)
            if st != f.stamp_ns:
                assert not np.allclose(img.T_world_ee, f.T_world_ee, atol=1e-9)
            shape = (CAMERA.height, CAMERA.width) if name in ("front", "side") else (TACTILE.height, TACTILE.width)
            expected = image_of(name, k, shape)  # raw and png are lossless
            if name in ("left", "right"):  # the tactile camera has lens distortion: undistorted
                mx, my = undistort_maps(TACTILE)
                expected = cv2.remap(expected, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            np.testing.assert_array_equal(img.image, expected)
            assert img.image.dtype == np.uint8 and img.image.shape == (*shape, 3)
        np.testing.assert_allclose(f.cameras["front"].T_world_sensor, sc.T_world_front, atol=1e-12)
        np.testing.assert_allclose(f.cameras["front"].camera.K, CAMERA.K)
        left, right = f.tactile["left"], f.tactile["right"]
        np.testing.assert_allclose(left.T_world_sensor, sc.T_world_ee(left.stamp_ns) @ sc.T_ee_left, atol=1e-12)
        np.testing.assert_allclose(right.T_world_sensor, sc.T_world_ee(right.stamp_ns) @ sc.T_ee_right, atol=1e-12)
        # the renderers' pinhole model: same intrinsics, distortion removed from image and depth
        np.testing.assert_allclose(left.camera.K, TACTILE.K)
        assert not left.camera.has_distortion
        mx, my = undistort_maps(TACTILE)
        np.testing.assert_array_equal(left.depth, cv2.remap(depth_of(k), mx, my, cv2.INTER_NEAREST))
        assert left.depth.dtype == np.float32 and right.depth is None
        # contact: the latest Bool at or before the frame time (published every 10 ms)
        last_tick = T0 + ((f.stamp_ns - T0) // (10 * MS)) * 10 * MS
        assert f.contact is sc.contact(last_tick)
        assert f.finger_opening_m == pytest.approx(sc.opening(f.stamp_ns), abs=1e-12)
        np.testing.assert_allclose(f.T_world_object_gt, sc.T_world_obj(f.stamp_ns), atol=1e-12)


def test_stamps_are_ordered_and_contact_switches(scene_log):
    frames, _ = read_frames(scene_log)
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    assert [f.contact for f in frames] == [False] * 5 + [True] * 5


def test_short_latency_window_reports_late_tactile_images(scene_log):
    # Tactile images arrive 120-130 ms after their stamp; with a 10 ms window their frame
    # has already been emitted (cameras only), so they are reported as late, not misgrouped.
    frames, reader = read_frames(scene_log, max_latency_ns=10 * MS)
    assert len(frames) == N_FRAMES
    assert all(f.tactile == {} and "front" in f.cameras for f in frames[:-1])
    assert set(frames[-1].tactile) == {"left", "right"}  # the last frame waits for the end of the log
    late = [r for _, r in reader.skipped if "arrived after its frame was emitted" in r]
    assert len(late) == 3 * (N_FRAMES - 1)  # left image, left depth, right image
    assert all(r.startswith("/tactile/") for r in late)


def test_time_window_keeps_frames_by_stamp(scene_log):
    frames, reader = read_frames(scene_log, start_ns=trigger(3) - MS, end_ns=trigger(6))
    assert [f.stamp_ns for f in frames] == [trigger(k) - MS for k in (3, 4, 5, 6)]
    assert [f.index for f in frames] == [0, 1, 2, 3]
    # frames inside the window are complete even though their tactile images are logged late
    assert all(set(f.tactile) == {"left", "right"} for f in frames)
    assert reader.skipped == []


def test_iter_frames_opens_a_path(scene_log):
    frames = list(iter_frames(scene_log, SENSORS[:1], TOPICS))
    assert len(frames) == N_FRAMES
    assert all(set(f.cameras) == {"front"} and f.tactile == {} for f in frames)


def test_optional_topics_absent_give_none(scene_log):
    topics = LogTopics(contact="/no_contact", joint_states=None, ground_truth="/nothing", sync_tolerance_ns=5 * MS)
    with McapLog(scene_log) as log:
        f = next(iter(FrameReader(log, SENSORS[:1], topics)))
    assert f.contact is None and f.finger_opening_m is None and f.T_world_object_gt is None


def test_sensor_frame_not_in_tf_names_the_frame(scene_log):
    bad = SensorTopics("front", "camera", "/cameras/front/image", "/cameras/front/camera_info", frame_id="front_camera")
    with McapLog(scene_log) as log:
        with pytest.raises(
            LogError, match=r"scene\.mcap: frame 'front_camera' is not in the TF tree \(known frames: .*ee"
        ):
            list(FrameReader(log, [bad], TOPICS))


def test_ee_frame_not_in_tf_fails_before_any_frame(scene_log):
    with McapLog(scene_log) as log:
        reader = FrameReader(log, SENSORS[:1], LogTopics(ee_frame="tcp"))
        with pytest.raises(LogError, match=r"frame 'tcp' is not in the TF tree"):
            next(iter(reader))


def test_missing_image_topic_names_topic_and_expected_type(scene_log):
    with McapLog(scene_log) as log:
        with pytest.raises(
            LogError,
            match=r"scene\.mcap: topic '/cameras/top/image' not found "
            r"\(expected sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage for camera 'top'\)",
        ):
            FrameReader(log, [SensorTopics.default("top")], TOPICS)


def test_wrong_topic_type_is_reported(scene_log):
    wrong = SensorTopics("front", "camera", "/contact", "/cameras/front/camera_info")
    with McapLog(scene_log) as log:
        with pytest.raises(
            LogError, match=r"topic '/contact' has type 'std_msgs/msg/Bool' \(expected sensor_msgs/msg/Image"
        ):
            FrameReader(log, [wrong], TOPICS)


def test_sensor_description_is_validated():
    with pytest.raises(ValueError, match="modality"):
        SensorTopics("x", "lidar", "/a", "/b")


def test_unknown_image_encoding_in_a_log_names_file_topic_and_encoding(tmp_path):
    good, bad = tmp_path / "good.mcap", tmp_path / "bad.mcap"
    with LogWriter(good) as w:
        w.write_image("/cameras/front/image", np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8), T0, "front_optical")
    with McapLog(good) as log:
        raw = next(log.messages("/cameras/front/image", decode=False)).msg
    assert raw.count(b"rgb8\x00") == 1
    with LogWriter(bad) as w:
        w.write_tf([("world", "front_optical", np.eye(4))], T0, static=True)
        w.write_tf([("world", "ee", np.eye(4))], T0)
        w.write_camera_info("/cameras/front/camera_info", CAMERA, T0, "front_optical")
        w.write_raw("/cameras/front/image", "sensor_msgs/msg/Image", raw.replace(b"rgb8\x00", b"nv21\x00"), T0)
    with pytest.raises(
        LogError,
        match=r"bad\.mcap: topic '/cameras/front/image': unsupported colour image encoding 'nv21' "
        r"\(supported: rgb8, bgr8, .*\) \(stamp 1700000000000000000 ns\)",
    ):
        list(iter_frames(bad, SENSORS[:1], TOPICS))


def test_contact_from_wrench_with_hysteresis(tmp_path):
    """Without a Bool topic, contact comes from the force magnitude: on at >= 2 N, off at <= 1 N."""
    path = tmp_path / "wrench.mcap"
    forces = [0.0, 0.5, 1.5, 2.5, 1.5, 1.2, 0.9, 1.5, 3.0, 0.2]
    expected = [False, False, False, True, True, True, False, False, True, False]
    with LogWriter(path) as w:
        w.write_tf([("world", "front_optical", np.eye(4))], T0, static=True)
        for k, f in enumerate(forces):
            t = T0 + k * 100 * MS
            w.write_tf([("world", "ee", np.eye(4))], t)
            w.write_wrench("/wrench", [0.0, f * 0.6, f * 0.8], [0.0, 0.0, 0.0], t, "ee")
            w.write_camera_info("/cameras/front/camera_info", CAMERA, t, "front_optical")
            w.write_image(
                "/cameras/front/image", np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8), t, "front_optical"
            )
    topics = LogTopics(contact=None, joint_states=None, ground_truth=None, wrench="/wrench")
    frames = list(iter_frames(path, SENSORS[:1], topics))
    assert [f.contact for f in frames] == expected
    # with a Bool topic named but absent, the wrench is used as well
    frames = list(iter_frames(path, SENSORS[:1], LogTopics(joint_states=None, ground_truth=None, wrench="/wrench")))
    assert [f.contact for f in frames] == expected


URDF = """<robot name="test_arm">
<link name="base"/><link name="slider"/><link name="ee"/>
<joint name="lift" type="prismatic"><parent link="base"/><child link="slider"/>
  <origin xyz="0 0 0.5" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<joint name="wrist" type="revolute"><parent link="slider"/><child link="ee"/>
  <origin xyz="0.1 0 0" rpy="3.14159265358979 0 0"/><axis xyz="0 0 1"/>\
<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>"""


def test_end_effector_from_joint_states_and_urdf(tmp_path):
    """No ee TF in the log: forward kinematics of the URDF from /joint_states gives T_world_ee,
    interpolated at the image times like any TF edge."""
    from scipy.spatial.transform import Rotation

    urdf = tmp_path / "arm.urdf"
    urdf.write_text(URDF)
    path = tmp_path / "joints.mcap"
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = [0.3, -0.2, 0.0]

    def joints(t_s: float) -> tuple[float, float]:
        return 0.05 + 0.1 * t_s, 0.4 * t_s  # lift [m], wrist [rad]

    def ee_expected(t_s: float) -> np.ndarray:
        lift, wrist = joints(t_s)
        T = np.eye(4)
        T[:3, 3] = [0.1, 0.0, 0.5 + lift]
        T[:3, :3] = Rotation.from_euler("x", np.pi).as_matrix() @ Rotation.from_euler("z", wrist).as_matrix()
        return T_world_base @ T

    with LogWriter(path) as w:
        w.write_tf([("world", "base", T_world_base), ("world", "front_optical", np.eye(4))], T0, static=True)
        for k in range(21):  # joint states at 100 Hz
            t = T0 + k * 10 * MS
            w.write_joint_state("/joint_states", ["lift", "wrist", "finger_left_joint"], [*joints(k * 0.01), 0.01], t)
        for k in range(4):  # images at 15 ms offsets: between joint samples
            t = T0 + 15 * MS + k * 50 * MS
            w.write_camera_info("/cameras/front/camera_info", CAMERA, t, "front_optical")
            w.write_image(
                "/cameras/front/image", np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8), t, "front_optical"
            )
    topics = LogTopics(tf="/tf", contact=None, ground_truth=None, urdf=str(urdf))
    frames = list(iter_frames(path, SENSORS[:1], topics))
    assert len(frames) == 4
    for f in frames:
        t_s = (f.stamp_ns - T0) / 1e9
        # interpolation between 10 ms samples of a linear/constant-rate motion is exact
        np.testing.assert_allclose(f.T_world_ee, ee_expected(t_s), atol=1e-9)
        assert f.finger_opening_m == pytest.approx(0.01)
