"""Writer for ROS 2 MCAP logs (profile ros2, ros2msg schemas, CDR messages), as rosbag2 writes them.

Used by the simulator and for pose tracks. Output is deterministic: the same calls give
byte-identical files. The header's library field is the constant ``LIBRARY`` (mcap's
own writers put their package versions there), no wall-clock time is ever written (a
message's log time defaults to its stamp), and channels and schemas are numbered in
first-use order. The file is written under a temporary name and renamed when
``close()`` succeeds (see ``atomic``), so a failed run leaves no partial log.

Messages are CDR-encoded here (little endian, XCDR1 alignment relative to the 4-byte
encapsulation header); the tests check the bytes against mcap_ros2's own encoder.
"""

from __future__ import annotations

import contextlib
import os
import struct
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as _McapWriter

from ..geometry import se3
from ..geometry.camera import PinholeCamera
from . import ros2_msgs as rm
from .atomic import atomic_output
from .images import encode_compressed, encode_mask_png, encode_raw

LIBRARY = "mvtop"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

# rosbag2 records each channel's offered QoS as YAML. /tf_static is latched (durability
# 1 = transient local) so that `ros2 bag play` re-delivers it to late subscribers;
# everything else is reliable (1) and volatile (2), keep-last (1) with depth 10.
_QOS = (
    "- history: 1\n  depth: {depth}\n  reliability: 1\n  durability: {durability}\n"
    "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n"
    "  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
    "  avoid_ros_namespace_conventions: false"
)


class _Cdr:
    """Little-endian CDR serializer for the fixed message set of ``ros2_msgs``."""

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")  # encapsulation: CDR_LE, options 0

    def _align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += b"\x00" * pad

    def u8(self, v: int) -> None:
        self.buf.append(int(v) & 0xFF)

    def boolean(self, v: bool) -> None:
        self.buf.append(1 if v else 0)

    def u32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", int(v))

    def i32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", int(v))

    def f32(self, v: float) -> None:
        self._align(4)
        self.buf += struct.pack("<f", float(v))

    def f64(self, v: float) -> None:
        self._align(8)
        self.buf += struct.pack("<d", float(v))

    def f64_array(self, values: Any, fixed: int | None = None) -> None:
        arr = np.ascontiguousarray(np.asarray(values, dtype=np.float64).ravel(), dtype="<f8")
        if fixed is None:
            self.u32(len(arr))
        elif len(arr) != fixed:
            raise ValueError(f"expected {fixed} float64 values, got {len(arr)}")
        if len(arr):
            self._align(8)
            self.buf += arr.tobytes()

    def string(self, s: str) -> None:
        b = str(s).encode("utf-8")
        self.u32(len(b) + 1)
        self.buf += b + b"\x00"

    def strings(self, values: Sequence[str]) -> None:
        self.u32(len(values))
        for s in values:
            self.string(s)

    def byte_seq(self, data: bytes) -> None:
        self.u32(len(data))
        self.buf += data

    # --- composite types ---------------------------------------------------------------------

    def time(self, stamp_ns: int) -> None:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        if not -(2**31) <= sec < 2**31:
            raise ValueError(f"stamp {stamp_ns} ns does not fit builtin_interfaces/Time (int32 seconds)")
        self.i32(sec)
        self.u32(nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        self.time(stamp_ns)
        self.string(frame_id)

    def vec3(self, v: Any) -> None:
        x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
        self.f64(x)
        self.f64(y)
        self.f64(z)

    def quat(self, q: Any) -> None:
        x, y, z, w = np.asarray(q, dtype=np.float64).reshape(4)
        self.f64(x)
        self.f64(y)
        self.f64(z)
        self.f64(w)

    def pose(self, T: np.ndarray) -> None:
        self.vec3(T[:3, 3])
        self.quat(se3.to_quat_xyzw(T))

    def image_fields(self, f: dict[str, Any]) -> None:
        self.u32(f["height"])
        self.u32(f["width"])
        self.string(f["encoding"])
        self.u8(f["is_bigendian"])
        self.u32(f["step"])
        self.byte_seq(f["data"])


def _check_pose(T: Any, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: expected a finite (4, 4) pose, got shape {T.shape}")
    return T


class LogWriter:
    """Write a ROS 2 MCAP log to ``path`` (atomically: it appears only when closed cleanly).

    ``compression`` is ``zstd`` (default), ``lz4`` or ``none`` (chunks stored as is);
    ``chunk_size`` [bytes] bounds a chunk before compression. Stamps and log times are
    int nanoseconds; each ``write_*`` takes ``log_time_ns`` (default: the stamp).

    Use as a context manager: on an exception inside the block the temporary file is
    deleted and nothing is written under ``path``.
    """

    def __init__(self, path: str | os.PathLike[str], *, compression: str = "zstd", chunk_size: int = 1 << 20):
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, not {compression!r}")
        self.path = path
        self._stack = contextlib.ExitStack()
        fh = self._stack.enter_context(atomic_output(path))
        self._writer = _McapWriter(fh, chunk_size=chunk_size, compression=COMPRESSIONS[compression], enable_crcs=True)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._sequence: dict[str, int] = {}
        self._open = True

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self._abort(exc_type, exc, tb)

    def close(self) -> None:
        """Finish the MCAP (summary, footer) and move the file to its final name."""
        if not self._open:
            return
        try:
            self._writer.finish()
        except BaseException:
            self._abort(*sys.exc_info())
            raise
        self._open = False
        self._stack.close()

    def abort(self) -> None:
        """Discard everything written so far; no file is left under ``path``."""
        try:
            raise RuntimeError("log writing aborted")
        except RuntimeError:
            self._abort(*sys.exc_info())

    def _abort(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if not self._open:
            return
        self._open = False
        with contextlib.suppress(BaseException):
            # atomic_output deletes its temporary file and re-raises; swallow the re-raise.
            self._stack.__exit__(exc_type, exc, tb)

    # --- low level -------------------------------------------------------------------------

    def _channel(self, topic: str, type_name: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != type_name:
                raise ValueError(f"topic {topic!r} already carries {known[1]}, cannot write {type_name}")
            return known[0]
        schema_id = self._schema_ids.get(type_name)
        if schema_id is None:
            schema_id = self._writer.register_schema(type_name, "ros2msg", rm.definition(type_name).encode())
            self._schema_ids[type_name] = schema_id
        qos = _QOS.format(
            depth=1 if topic.endswith("tf_static") else 10, durability=1 if topic.endswith("tf_static") else 2
        )
        cid = self._writer.register_channel(topic, "cdr", schema_id, {"offered_qos_profiles": qos})
        self._channels[topic] = (cid, type_name)
        return cid

    def write_raw(
        self, topic: str, type_name: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Write already CDR-encoded ``data`` as a message of ``type_name`` (``pkg/msg/Name``)."""
        if not self._open:
            raise ValueError(f"{self.path}: writer is closed")
        type_name = rm.normalize_type(type_name)
        cid = self._channel(topic, type_name)
        seq = self._sequence.get(topic, 0)
        self._sequence[topic] = seq + 1
        log_time_ns = int(log_time_ns)
        self._writer.add_message(
            channel_id=cid,
            log_time=log_time_ns,
            publish_time=log_time_ns if publish_time_ns is None else int(publish_time_ns),
            sequence=seq & 0xFFFFFFFF,
            data=bytes(data),
        )

    def _write(self, topic: str, type_name: str, fill: Callable[[_Cdr], None], log_time_ns: int) -> None:
        c = _Cdr()
        fill(c)
        self.write_raw(topic, type_name, bytes(c.buf), log_time_ns)

    # --- typed helpers ---------------------------------------------------------------------

    def write_tf(
        self,
        transforms: Iterable[tuple[str, str, np.ndarray]],
        stamp_ns: int,
        *,
        static: bool = False,
        topic: str | None = None,
        log_time_ns: int | None = None,
    ) -> None:
        """One tf2_msgs/TFMessage of ``(parent, child, T_parent_child)`` triples, all at ``stamp_ns``.

        ``topic`` defaults to ``/tf_static`` when ``static`` else ``/tf``.
        """
        items = [(p, ch, _check_pose(T, f"transform {p} -> {ch}")) for p, ch, T in transforms]

        def fill(c: _Cdr) -> None:
            c.u32(len(items))
            for parent, child, T in items:
                c.header(stamp_ns, parent)
                c.string(child)
                c.vec3(T[:3, 3])
                c.quat(se3.to_quat_xyzw(T))

        topic = topic or ("/tf_static" if static else "/tf")
        self._write(topic, rm.TF_MESSAGE, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_image(
        self,
        topic: str,
        image: np.ndarray,
        stamp_ns: int,
        frame_id: str,
        *,
        encoding: str = "rgb8",
        log_time_ns: int | None = None,
    ) -> None:
        """A raw sensor_msgs/Image: (H, W, 3) uint8 RGB for rgb8/bgr8, (H, W) uint8 for mono8,
        (H, W) depth [m] for 32FC1 / 16UC1 (see ``images.encode_raw``)."""
        fields = encode_raw(image, encoding)

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.image_fields(fields)

        self._write(topic, rm.IMAGE, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_depth(
        self, topic: str, depth_m: np.ndarray, stamp_ns: int, frame_id: str, *, log_time_ns: int | None = None
    ) -> None:
        """A 32FC1 sensor_msgs/Image of depth (H, W) [m] (gel indentation for tactile sensors)."""
        self.write_image(topic, depth_m, stamp_ns, frame_id, encoding="32FC1", log_time_ns=log_time_ns)

    def write_compressed_image(
        self,
        topic: str,
        rgb: np.ndarray,
        stamp_ns: int,
        frame_id: str,
        *,
        fmt: str = "png",
        jpeg_quality: int = 95,
        log_time_ns: int | None = None,
    ) -> None:
        """A sensor_msgs/CompressedImage of an (H, W, 3) uint8 RGB image, png or jpeg."""
        fields = encode_compressed(rgb, fmt, jpeg_quality)

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.string(fields["format"])
            c.byte_seq(fields["data"])

        self._write(topic, rm.COMPRESSED_IMAGE, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_mask(
        self,
        topic: str,
        labels: np.ndarray,
        stamp_ns: int,
        frame_id: str,
        *,
        fmt: str = "raw",
        log_time_ns: int | None = None,
    ) -> None:
        """A recorded object mask (H, W) uint8 or uint16 labels (0 = background), as an
        external segmenter publishes it: ``fmt`` ``raw`` (sensor_msgs/Image mono8 or mono16)
        or ``png`` (a one-channel sensor_msgs/CompressedImage)."""
        labels = np.asarray(labels)
        log_time = stamp_ns if log_time_ns is None else log_time_ns
        if fmt == "raw":
            encoding = "mono8" if labels.dtype == np.uint8 else "mono16"
            self.write_image(topic, labels, stamp_ns, frame_id, encoding=encoding, log_time_ns=log_time)
            return
        if fmt != "png":
            raise ValueError(f"mask format must be 'raw' or 'png', not {fmt!r}")
        fields = encode_mask_png(labels)

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.string(fields["format"])
            c.byte_seq(fields["data"])

        self._write(topic, rm.COMPRESSED_IMAGE, fill, log_time)

    def write_camera_info(
        self, topic: str, camera: PinholeCamera, stamp_ns: int, frame_id: str, *, log_time_ns: int | None = None
    ) -> None:
        """A sensor_msgs/CameraInfo from a PinholeCamera (r = identity, p = [K | 0])."""
        K = np.asarray(camera.K, dtype=np.float64).reshape(3, 3)
        P = np.hstack([K, np.zeros((3, 1))])

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.u32(camera.height)
            c.u32(camera.width)
            c.string(camera.distortion_model)
            c.f64_array(camera.distortion)
            c.f64_array(K, fixed=9)
            c.f64_array(np.eye(3), fixed=9)
            c.f64_array(P, fixed=12)
            c.u32(0)  # binning_x
            c.u32(0)  # binning_y
            for _ in range(4):  # roi: x_offset, y_offset, height, width (all 0: full image)
                c.u32(0)
            c.boolean(False)  # roi.do_rectify

        self._write(topic, rm.CAMERA_INFO, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_joint_state(
        self,
        topic: str,
        names: Sequence[str],
        positions: Sequence[float],
        stamp_ns: int,
        *,
        velocities: Sequence[float] = (),
        efforts: Sequence[float] = (),
        log_time_ns: int | None = None,
    ) -> None:
        """A sensor_msgs/JointState: positions [m or rad] per joint name."""
        if len(positions) != len(names):
            raise ValueError(f"{len(names)} joint names but {len(positions)} positions")

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, "")
            c.strings(list(names))
            c.f64_array(positions)
            c.f64_array(velocities)
            c.f64_array(efforts)

        self._write(topic, rm.JOINT_STATE, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_bool(self, topic: str, value: bool, log_time_ns: int) -> None:
        """A std_msgs/Bool (it has no header: its time is the log time)."""
        self._write(topic, rm.BOOL, lambda c: c.boolean(value), log_time_ns)

    def write_wrench(
        self,
        topic: str,
        force: Sequence[float],
        torque: Sequence[float],
        stamp_ns: int,
        frame_id: str,
        *,
        log_time_ns: int | None = None,
    ) -> None:
        """A geometry_msgs/WrenchStamped: force (3,) [N], torque (3,) [N m] in ``frame_id``."""

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.vec3(force)
            c.vec3(torque)

        self._write(topic, rm.WRENCH_STAMPED, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_pose(
        self, topic: str, T: np.ndarray, stamp_ns: int, frame_id: str, *, log_time_ns: int | None = None
    ) -> None:
        """A geometry_msgs/PoseStamped from a (4, 4) pose ``T_frame_x``."""
        T = _check_pose(T, f"pose on {topic}")

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.pose(T)

        self._write(topic, rm.POSE_STAMPED, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_pose_array(
        self, topic: str, Ts: np.ndarray, stamp_ns: int, frame_id: str, *, log_time_ns: int | None = None
    ) -> None:
        """A geometry_msgs/PoseArray from (n, 4, 4) poses (e.g. particles of the filter)."""
        Ts = np.asarray(Ts, dtype=np.float64)
        if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
            raise ValueError(f"pose array on {topic}: expected (n, 4, 4) poses, got shape {Ts.shape}")
        quats = se3.to_quat_xyzw(Ts) if len(Ts) else np.zeros((0, 4))

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.u32(len(Ts))
            for T, q in zip(Ts, quats):
                c.vec3(T[:3, 3])
                c.quat(q)

        self._write(topic, rm.POSE_ARRAY, fill, stamp_ns if log_time_ns is None else log_time_ns)

    def write_triangle_marker(
        self,
        topic: str,
        triangles: np.ndarray,
        stamp_ns: int,
        frame_id: str,
        *,
        rgba: Sequence[float] = (0.2, 0.6, 1.0, 0.8),
        ns: str = "",
        marker_id: int = 0,
        frame_locked: bool = True,
        log_time_ns: int | None = None,
    ) -> None:
        """A visualization_msgs/Marker TRIANGLE_LIST of ``triangles`` (k, 3, 3) [m] in
        ``frame_id`` (identity pose, unit scale, one colour, no lifetime: it stays until
        replaced); ``frame_locked`` makes viewers move it with ``frame_id`` as TF changes."""
        tri = np.ascontiguousarray(np.asarray(triangles, dtype="<f8").reshape(-1, 3))
        if not np.all(np.isfinite(tri)):
            raise ValueError(f"marker on {topic}: triangle corners must be finite")

        def fill(c: _Cdr) -> None:
            c.header(stamp_ns, frame_id)
            c.string(ns)
            c.i32(marker_id)
            c.i32(11)  # TRIANGLE_LIST
            c.i32(0)  # ADD
            c.pose(np.eye(4))
            c.vec3((1.0, 1.0, 1.0))
            for v in rgba:
                c.f32(v)
            c.i32(0)  # lifetime: forever
            c.u32(0)
            c.boolean(frame_locked)
            c.u32(len(tri))
            if len(tri):
                c._align(8)
                c.buf += tri.tobytes()
            c.u32(0)  # colors
            c.string("")  # texture_resource
            c.header(0, "")  # texture: an empty CompressedImage
            c.string("")
            c.u32(0)
            c.u32(0)  # uv_coordinates
            c.string("")  # text
            c.string("")  # mesh_resource
            c.string("")  # mesh_file.filename
            c.u32(0)  # mesh_file.data
            c.boolean(False)  # mesh_use_embedded_materials

        self._write(topic, rm.MARKER, fill, stamp_ns if log_time_ns is None else log_time_ns)
