"""ROS 2 definitions: rosbag2's concatenated layout, accepted by mcap_ros2's writer and decoder."""

from __future__ import annotations

import io

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from mvtop_cli.io import ros2_msgs as rm

REQUIRED = [
    rm.TF_MESSAGE, rm.IMAGE, rm.COMPRESSED_IMAGE, rm.CAMERA_INFO, rm.JOINT_STATE,
    rm.BOOL, rm.WRENCH_STAMPED, rm.POSE_STAMPED, rm.POSE_ARRAY,
]


def test_layout_matches_rosbag2():
    text = rm.definition("sensor_msgs/msg/CameraInfo")
    sep = "\n" + "=" * 80 + "\n"
    parts = text.split(sep)
    assert [p.splitlines()[0] for p in parts[1:]] == [
        "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time", "MSG: sensor_msgs/RegionOfInterest",
    ]
    assert "float64[9] k" in parts[0] and "RegionOfInterest roi" in parts[0]
    # each dependency once, depth first in field order
    assert rm.dependencies(rm.TF_MESSAGE) == [
        "geometry_msgs/msg/TransformStamped", "std_msgs/msg/Header", "builtin_interfaces/msg/Time",
        "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion",
    ]
    assert rm.definition("std_msgs/Bool") == "bool data\n"
    assert rm.normalize_type("sensor_msgs/Image") == rm.IMAGE
    with pytest.raises(KeyError, match="no ROS 2 definition for 'foo/msg/Bar'"):
        rm.definition("foo/msg/Bar")


def test_mcap_ros2_writer_encodes_every_type_and_decodes_it_back():
    stamp = {"sec": 1_700_000_000, "nanosec": 5}
    header = {"stamp": stamp, "frame_id": "world"}
    vec = {"x": 1.0, "y": -2.0, "z": 3.5}
    quat = {"x": 0.0, "y": 0.0, "z": 0.6, "w": 0.8}
    pose = {"position": vec, "orientation": quat}
    samples = {
        rm.TF_MESSAGE: {"transforms": [{"header": header, "child_frame_id": "ee",
                                        "transform": {"translation": vec, "rotation": quat}}]},
        rm.IMAGE: {"header": header, "height": 1, "width": 2, "encoding": "rgb8", "is_bigendian": 0, "step": 6,
                   "data": bytes(range(6))},
        rm.COMPRESSED_IMAGE: {"header": header, "format": "png", "data": b"\x89PNG"},
        rm.CAMERA_INFO: {"header": header, "height": 4, "width": 5, "distortion_model": "plumb_bob", "d": [0.1] * 5,
                          "k": [float(i) for i in range(9)], "r": [0.0] * 9, "p": [0.0] * 12, "binning_x": 0,
                          "binning_y": 0,
                          "roi": {"x_offset": 1, "y_offset": 2, "height": 3, "width": 4, "do_rectify": True}},
        rm.JOINT_STATE: {"header": header, "name": ["finger_joint1"], "position": [0.01], "velocity": [], "effort": []},
        rm.BOOL: {"data": True},
        rm.WRENCH_STAMPED: {"header": header, "wrench": {"force": vec, "torque": vec}},
        rm.POSE_STAMPED: {"header": header, "pose": pose},
        rm.POSE_ARRAY: {"header": header, "poses": [pose, pose]},
    }
    buf = io.BytesIO()
    writer = Ros2Writer(buf)
    for type_name in REQUIRED:
        schema = writer.register_msgdef(type_name, rm.definition(type_name))
        writer.write_message(f"/{type_name.split('/')[-1]}", schema, samples[type_name], log_time=1)
    writer.finish()
    reader = make_reader(io.BytesIO(buf.getvalue()), decoder_factories=[DecoderFactory()])
    decoded = {schema.name: msg for schema, _ch, _m, msg in reader.iter_decoded_messages()}
    assert sorted(decoded) == sorted(REQUIRED)
    assert decoded[rm.TF_MESSAGE].transforms[0].child_frame_id == "ee"
    assert decoded[rm.TF_MESSAGE].transforms[0].transform.rotation.w == 0.8
    assert decoded[rm.IMAGE].data == bytes(range(6))
    assert list(decoded[rm.CAMERA_INFO].k) == [float(i) for i in range(9)]
    assert decoded[rm.CAMERA_INFO].roi.do_rectify is True
    assert decoded[rm.JOINT_STATE].name == ["finger_joint1"]
    assert decoded[rm.POSE_ARRAY].poses[1].position.z == 3.5
    assert decoded[rm.WRENCH_STAMPED].wrench.torque.y == -2.0
    assert decoded[rm.POSE_STAMPED].header.stamp.nanosec == 5
