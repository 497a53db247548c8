"""Log writer: every message type in every compression reads back; CDR bytes equal mcap_ros2's;
output is deterministic and atomic."""

from __future__ import annotations

import io

import numpy as np
import pytest
from _io_scene import MS, T0
from mcap.reader import make_reader
from mcap_ros2.writer import Writer as Ros2Writer

from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.io import ros2_msgs as rm
from mvtop_cli.io.frames import camera_from_info
from mvtop_cli.io.images import decode_depth, decode_image
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LIBRARY, LogWriter
from mvtop_cli.io.tf_buffer import stamp_to_ns

RNG = np.random.default_rng(11)
T = se3.make_pose(se3.rotvec_to_matrix([0.1, -0.2, 0.3]), [0.4, 0.5, -0.6])
TS = se3.make_pose(se3.rotvec_to_matrix(RNG.normal(size=(5, 3))), RNG.normal(size=(5, 3)))
RGB = RNG.integers(0, 256, (10, 14, 3), dtype=np.uint8)
_yy, _xx = np.mgrid[0:10, 0:14]
SMOOTH = np.stack([_xx * 12, _yy * 15, (_xx + _yy) * 8], axis=-1).astype(np.uint8)  # jpeg-friendly
DEPTH = RNG.uniform(0, 0.002, (10, 14)).astype(np.float32)
CAM = PinholeCamera(width=14, height=10, K=np.array([[20.0, 0, 6.5], [0, 21.0, 4.5], [0, 0, 1]]),
                    distortion_model="rational_polynomial", distortion=np.arange(8) * 0.01)


def write_everything(path, compression="zstd"):
    with LogWriter(path, compression=compression) as w:
        w.write_tf([("world", "base", T)], T0, static=True)
        w.write_tf([("base", "ee", T), ("ee", "tcp", np.eye(4))], T0 + 1 * MS)
        w.write_image("/cameras/front/image", RGB, T0 + 2 * MS, "front_optical")
        w.write_image("/cameras/mono/image", RGB[..., 0], T0 + 2 * MS, "mono_optical", encoding="mono8")
        w.write_compressed_image("/cameras/side/image/compressed", RGB, T0 + 3 * MS, "side_optical", fmt="png")
        w.write_compressed_image("/cameras/top/image/compressed", SMOOTH, T0 + 3 * MS, "top_optical", fmt="jpeg")
        w.write_camera_info("/cameras/front/camera_info", CAM, T0 + 2 * MS, "front_optical")
        w.write_depth("/tactile/left/depth", DEPTH, T0 + 4 * MS, "tactile_left_optical")
        w.write_joint_state("/joint_states", ["finger_joint1", "finger_joint2"], [0.01, 0.0125], T0 + 5 * MS,
                            velocities=[0.1, 0.2])
        w.write_bool("/contact", True, T0 + 6 * MS)
        w.write_wrench("/wrench", [1.0, 2.0, 3.0], [0.1, 0.2, 0.3], T0 + 7 * MS, "ee")
        w.write_pose("/ground_truth/object_pose", T, T0 + 8 * MS, "world", log_time_ns=T0 + 9 * MS)
        w.write_pose_array("/estimate/particles", TS, T0 + 10 * MS, "world")


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_type_reads_back(tmp_path, compression):
    path = tmp_path / "all.mcap"
    write_everything(path, compression)
    with McapLog(path) as log:
        s = log.summary()
        assert s.profile == "ros2" and s.library == LIBRARY and s.indexed
        assert s.compression == (compression,)
        assert s.message_count == 13 and len(s.topics) == 13
        assert s.topic("/estimate/particles").type == rm.POSE_ARRAY
        assert s.topic("/ground_truth/object_pose").first_ns == T0 + 9 * MS  # log time, not the stamp
        msgs = {m.topic: m for m in log.messages()}

    tf_static = msgs["/tf_static"].msg.transforms[0]
    assert (tf_static.header.frame_id, tf_static.child_frame_id) == ("world", "base")
    q = tf_static.transform.rotation
    np.testing.assert_allclose(se3.from_quat_xyzw([q.x, q.y, q.z, q.w], [0, 0, 0])[:3, :3], T[:3, :3], atol=1e-12)
    tf = msgs["/tf"].msg.transforms
    assert [t.child_frame_id for t in tf] == ["ee", "tcp"] and stamp_to_ns(tf[0].header.stamp) == T0 + MS

    img = msgs["/cameras/front/image"].msg
    assert (img.encoding, img.header.frame_id, stamp_to_ns(img.header.stamp)) == ("rgb8", "front_optical", T0 + 2 * MS)
    np.testing.assert_array_equal(decode_image(img), RGB)
    np.testing.assert_array_equal(decode_image(msgs["/cameras/mono/image"].msg)[..., 2], RGB[..., 0])
    np.testing.assert_array_equal(decode_image(msgs["/cameras/side/image/compressed"].msg), RGB)
    jpeg = decode_image(msgs["/cameras/top/image/compressed"].msg)
    assert jpeg.shape == SMOOTH.shape and np.abs(jpeg.astype(int) - SMOOTH).mean() < 3.0  # lossy but close
    np.testing.assert_array_equal(decode_depth(msgs["/tactile/left/depth"].msg), DEPTH)

    cam = camera_from_info(msgs["/cameras/front/camera_info"].msg)
    assert (cam.width, cam.height, cam.distortion_model) == (14, 10, "rational_polynomial")
    np.testing.assert_array_equal(cam.K, CAM.K)
    np.testing.assert_array_equal(cam.distortion, CAM.distortion)
    info = msgs["/cameras/front/camera_info"].msg
    np.testing.assert_array_equal(np.reshape(info.p, (3, 4))[:, :3], CAM.K)

    js = msgs["/joint_states"].msg
    assert js.name == ["finger_joint1", "finger_joint2"] and list(js.position) == [0.01, 0.0125]
    assert list(js.velocity) == [0.1, 0.2] and list(js.effort) == []
    assert msgs["/contact"].msg.data is True and msgs["/contact"].log_time_ns == T0 + 6 * MS
    wr = msgs["/wrench"].msg.wrench
    assert (wr.force.x, wr.force.z, wr.torque.y) == (1.0, 3.0, 0.2)

    p = msgs["/ground_truth/object_pose"].msg.pose
    got = se3.from_quat_xyzw([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w],
                             [p.position.x, p.position.y, p.position.z])
    np.testing.assert_allclose(got, T, atol=1e-12)
    poses = msgs["/estimate/particles"].msg.poses
    got = np.stack([se3.from_quat_xyzw([q.orientation.x, q.orientation.y, q.orientation.z, q.orientation.w],
                                       [q.position.x, q.position.y, q.position.z]) for q in poses])
    np.testing.assert_allclose(got, TS, atol=1e-12)


def test_cdr_bytes_equal_mcap_ros2_encoder(tmp_path):
    """Our encoder against mcap_ros2's generic one, field for field."""
    path = tmp_path / "mine.mcap"
    write_everything(path, "none")
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        mine = {ch.topic: (schema.name, m.data) for schema, ch, m in reader.iter_messages()}
    with McapLog(path) as log:
        decoded = {m.topic: m for m in log.messages()}

    def as_dict(obj):
        if hasattr(obj, "__slots__"):
            return {k: as_dict(getattr(obj, k)) for k in obj.__slots__}
        if isinstance(obj, list):
            return [as_dict(v) for v in obj]
        return obj

    buf = io.BytesIO()
    ref_writer = Ros2Writer(buf, compression=__import__("mcap.writer").writer.CompressionType.NONE)
    schemas = {}
    for topic, (type_name, _data) in mine.items():
        if type_name not in schemas:
            schemas[type_name] = ref_writer.register_msgdef(type_name, rm.definition(type_name))
        ref_writer.write_message(topic, schemas[type_name], as_dict(decoded[topic].msg), log_time=1)
    ref_writer.finish()
    ref = {ch.topic: m.data for _s, ch, m in make_reader(io.BytesIO(buf.getvalue())).iter_messages()}
    assert set(ref) == set(mine)
    for topic in mine:
        assert mine[topic][1] == ref[topic], topic


def test_same_input_gives_identical_bytes(tmp_path):
    for compression in ("zstd", "lz4", "none"):
        a, b = tmp_path / f"a_{compression}.mcap", tmp_path / f"b_{compression}.mcap"
        write_everything(a, compression)
        write_everything(b, compression)
        assert a.read_bytes() == b.read_bytes()
    data = (tmp_path / "a_zstd.mcap").read_bytes()
    assert b"mcap-python" not in data and b"mcap-ros2-support" not in data  # no library versions


def test_channels_carry_qos_like_rosbag2(tmp_path):
    path = tmp_path / "qos.mcap"
    write_everything(path)
    with open(path, "rb") as fh:
        channels = {c.topic: c for c in make_reader(fh).get_summary().channels.values()}
    assert "durability: 1" in channels["/tf_static"].metadata["offered_qos_profiles"]  # transient local
    assert "durability: 2" in channels["/tf"].metadata["offered_qos_profiles"]


def test_exception_inside_the_writer_leaves_no_file(tmp_path):
    path = tmp_path / "broken.mcap"
    with pytest.raises(ZeroDivisionError):
        with LogWriter(path) as w:
            w.write_bool("/contact", True, T0)
            _ = 1 / 0
    assert list(tmp_path.iterdir()) == []
    w = LogWriter(path)
    w.write_bool("/contact", True, T0)
    w.abort()
    assert list(tmp_path.iterdir()) == []


def test_writer_rejects_misuse(tmp_path):
    with pytest.raises(ValueError, match="compression must be one of zstd, lz4, none"):
        LogWriter(tmp_path / "x.mcap", compression="bz2")
    with LogWriter(tmp_path / "y.mcap") as w:
        w.write_bool("/contact", True, T0)
        with pytest.raises(ValueError, match="topic '/contact' already carries std_msgs/msg/Bool"):
            w.write_pose("/contact", np.eye(4), T0, "world")
        with pytest.raises(ValueError, match=r"expected a finite \(4, 4\) pose"):
            w.write_pose("/p", np.eye(3), T0, "world")
        with pytest.raises(ValueError, match="2 joint names but 1 positions"):
            w.write_joint_state("/joint_states", ["a", "b"], [0.0], T0)
    assert (tmp_path / "y.mcap").exists()


def test_triangle_marker_bytes_equal_mcap_ros2_encoder(tmp_path):
    """The Marker (Humble definition) against mcap_ros2's generic encoder, and decoded back."""
    tri = np.arange(2 * 9, dtype=float).reshape(2, 3, 3) * 1e-3
    path = tmp_path / "marker.mcap"
    with LogWriter(path, compression="none") as w:
        w.write_triangle_marker("/model", tri, T0, "object_estimate", rgba=(0.25, 0.5, 0.75, 1.0), ns="object")
    with open(path, "rb") as fh:
        ((_s, _c, mine),) = list(make_reader(fh).iter_messages())
    header = {"stamp": {"sec": T0 // 10**9, "nanosec": T0 % 10**9}, "frame_id": "object_estimate"}
    msg = {
        "header": header, "ns": "object", "id": 0, "type": 11, "action": 0,
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "scale": {"x": 1.0, "y": 1.0, "z": 1.0}, "color": {"r": 0.25, "g": 0.5, "b": 0.75, "a": 1.0},
        "lifetime": {"sec": 0, "nanosec": 0}, "frame_locked": True,
        "points": [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in tri.reshape(-1, 3)],
        "colors": [], "texture_resource": "",
        "texture": {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}, "format": "", "data": b""},
        "uv_coordinates": [], "text": "", "mesh_resource": "", "mesh_file": {"filename": "", "data": b""},
        "mesh_use_embedded_materials": False,
    }
    buf = io.BytesIO()
    ref_writer = Ros2Writer(buf, compression=__import__("mcap.writer").writer.CompressionType.NONE)
    schema = ref_writer.register_msgdef(rm.MARKER, rm.definition(rm.MARKER))
    ref_writer.write_message("/model", schema, msg, log_time=T0)
    ref_writer.finish()
    ((_s, _c, ref),) = list(make_reader(io.BytesIO(buf.getvalue())).iter_messages())
    assert mine.data == ref.data
    with McapLog(path) as log:
        (m,) = list(log.messages())
    assert [(p.x, p.y, p.z) for p in m.msg.points] == [tuple(p) for p in tri.reshape(-1, 3)]
