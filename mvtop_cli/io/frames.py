"""Group a log's sensor images into time-ordered observation frames (``records.Frame``).

Callers describe the sensors with plain ``SensorTopics`` and the rest of the topic
layout with ``LogTopics``, so this module does not depend on the config.

Reading is two passes. Pass 1 reads the small topics in one go (TF, contact, joint
states, ground truth, camera infos) into compact arrays. Pass 2 streams the image
topics in log-time order and groups them: images (and depth maps) whose stamps (header
stamps; the log time when a stamp is zero) all lie within ``sync_tolerance_ns`` of each
other form one frame, one image per sensor; a camera's recorded object mask (``mask_topic``)
joins its image the same way, and a camera image without its mask is skipped. A frame is emitted as soon as every sensor
has delivered, or once the stream's newest stamp is ``max_latency_ns`` past it, so only
a bounded window of images is in memory; a frame missing a sensor is emitted with the
sensors it has. The frame's time is the earliest image stamp in it; each sensor's pose
is looked up at its own stamp.
"""

from __future__ import annotations

from array import array
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LogError
from ..geometry.camera import PinholeCamera
from ..records import Frame, SensorImage
from . import ros2_msgs as rm
from .images import decode_depth, decode_image, decode_mask
from .mcap_reader import LogMessage, McapLog
from .tf_buffer import PoseSeries, TfBuffer, stamp_to_ns, valid_transform

MODALITIES = ("camera", "tactile")


@dataclass(frozen=True)
class SensorTopics:
    """Where one camera or tactile sensor publishes.

    ``image_topic`` carries sensor_msgs Image or CompressedImage; ``info_topic`` its
    CameraInfo; ``depth_topic`` an optional 32FC1 Image [m]; ``frame_id`` the optical
    frame in TF (default: the CameraInfo header's frame_id, else the image's);
    ``mask_topic`` the object masks an external segmenter publishes for the images
    (sensor_msgs Image mono8/mono16 or a png CompressedImage, see ``images.decode_mask``).
    """

    name: str
    modality: str
    image_topic: str
    info_topic: str
    depth_topic: str | None = None
    frame_id: str | None = None
    mask_topic: str | None = None

    def __post_init__(self) -> None:
        if self.modality not in MODALITIES:
            raise ValueError(f"sensor {self.name!r}: modality must be one of {MODALITIES}, not {self.modality!r}")

    @classmethod
    def default(
        cls, name: str, modality: str = "camera", *, compressed: bool = False, depth: bool = False
    ) -> SensorTopics:
        """The default layout: ``/cameras/<name>/...`` or ``/tactile/<name>/...``."""
        prefix = "/cameras" if modality == "camera" else "/tactile"
        image = f"{prefix}/{name}/image" + ("/compressed" if compressed else "")
        return cls(
            name=name,
            modality=modality,
            image_topic=image,
            info_topic=f"{prefix}/{name}/camera_info",
            depth_topic=f"{prefix}/{name}/depth" if depth else None,
        )


@dataclass(frozen=True)
class LogTopics:
    """The non-image topics and frame names of a log; optional topics may be None or absent."""

    tf: str = "/tf"
    tf_static: str = "/tf_static"
    contact: str | None = "/contact"
    joint_states: str | None = "/joint_states"
    ground_truth: str | None = "/ground_truth/object_pose"
    world_frame: str = "world"
    ee_frame: str = "ee"
    sync_tolerance_ns: int = 10_000_000
    # Contact from a force sensor instead of a Bool: geometry_msgs/WrenchStamped on ``wrench``
    # (used when ``contact`` is None or absent), with hysteresis: contact starts when the force
    # magnitude reaches ``contact_force_on_n`` [N] and ends when it falls to ``contact_force_off_n``.
    wrench: str | None = None
    contact_force_on_n: float = 2.0
    contact_force_off_n: float = 1.0
    # A URDF for logs without the end effector's TF: its links are added to TF from the
    # joint states (forward kinematics), rooted at the URDF's base link.
    urdf: str | None = None


def header_stamp_ns(msg: Any, log_time_ns: int) -> int:
    """The message's header stamp [ns], or ``log_time_ns`` when the stamp is zero."""
    t = stamp_to_ns(msg.header.stamp)
    return t if t != 0 else log_time_ns


_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


def undistort_maps(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (H, W) float32 that undistort an image of ``camera`` into a pinhole image
    with the same intrinsics ``K`` (OpenCV's model: ``plumb_bob`` k1 k2 p1 p2 k3,
    ``rational_polynomial`` k1 k2 p1 p2 k3 k4 k5 k6)."""
    import cv2

    D = np.asarray(camera.distortion, dtype=np.float64).ravel()
    return cv2.initUndistortRectifyMap(camera.K, D, None, camera.K, (camera.width, camera.height), cv2.CV_32FC1)


# Coefficient counts OpenCV reads for each supported model (ROS: 5 and 8).
_DISTORTION_COUNTS = {"plumb_bob": (4, 5), "rational_polynomial": (8, 12, 14)}
MAX_IMAGE_SIDE_PX = 16384  # beyond any camera or tactile sensor; bounds the undistortion tables


def camera_from_info(msg: Any, topic: str = "") -> PinholeCamera:
    """A PinholeCamera from a decoded sensor_msgs/CameraInfo; LogError naming ``topic`` when
    the size, intrinsics ``k`` [px] or distortion coefficients ``d`` are unusable."""
    width, height = int(msg.width), int(msg.height)
    if not (0 < width <= MAX_IMAGE_SIDE_PX and 0 < height <= MAX_IMAGE_SIDE_PX):
        raise LogError(
            f"topic {topic!r}: CameraInfo gives an image size of {width}x{height} px "
            f"(expected 1 to {MAX_IMAGE_SIDE_PX} px per side)"
        )
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise LogError(
            f"topic {topic!r}: CameraInfo has intrinsics k={K.ravel().tolist()} "
            "(expected finite numbers with a last row of 0, 0, 1)"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise LogError(
            f"topic {topic!r}: CameraInfo has focal lengths fx={K[0, 0]}, fy={K[1, 1]} "
            "(expected a calibrated camera with positive k[0] and k[4])"
        )
    model = str(msg.distortion_model) or "plumb_bob"
    D = np.asarray(msg.d, dtype=np.float64)
    if not np.all(np.isfinite(D)):
        raise LogError(
            f"topic {topic!r}: CameraInfo has distortion coefficients d={D.tolist()} (expected finite numbers)"
        )
    if np.any(D != 0) and model not in _DISTORTION_MODELS:
        raise LogError(
            f"topic {topic!r}: CameraInfo distortion model {model!r} is not supported "
            f"(expected {' or '.join(_DISTORTION_MODELS)}, or all-zero coefficients)"
        )
    if np.any(D != 0) and len(D) not in _DISTORTION_COUNTS[model]:
        expected = " or ".join(str(n) for n in _DISTORTION_COUNTS[model])
        raise LogError(
            f"topic {topic!r}: CameraInfo has {len(D)} distortion coefficients for model {model!r} "
            f"(expected {expected})"
        )
    return PinholeCamera(width=width, height=height, K=K, distortion_model=model, distortion=D)


@dataclass
class _Group:
    slots: dict[tuple[str, str], tuple[int, LogMessage]] = field(default_factory=dict)
    lo: int = 0
    hi: int = 0

    def fits(self, key: tuple[str, str], t: int, tol: int) -> bool:
        return key not in self.slots and max(self.hi, t) - min(self.lo, t) <= tol

    def add(self, key: tuple[str, str], t: int, m: LogMessage) -> None:
        if not self.slots:
            self.lo = self.hi = t
        self.slots[key] = (t, m)
        self.lo, self.hi = min(self.lo, t), max(self.hi, t)


class _Series:
    """Scalar samples (stamp [ns], value), collected in compact typed arrays and kept
    as sorted numpy arrays once finished."""

    def __init__(self) -> None:
        self._t = array("q")
        self._v = array("d")
        self.t = np.zeros(0, dtype=np.int64)
        self.v = np.zeros(0)

    def add(self, t: int, v: float) -> None:
        self._t.append(int(t))
        self._v.append(float(v))

    def finish(self) -> None:
        t = np.frombuffer(self._t, dtype=np.int64) if len(self._t) else np.zeros(0, dtype=np.int64)
        v = np.frombuffer(self._v, dtype=np.float64) if len(self._v) else np.zeros(0)
        order = np.argsort(t, kind="stable")
        self.t, self.v = t[order], v[order]
        self._t, self._v = array("q"), array("d")

    def latest(self, t_ns: int) -> float | None:
        """Value of the latest sample at or before ``t_ns`` (None before the first)."""
        i = int(np.searchsorted(self.t, t_ns, side="right")) - 1
        return None if i < 0 else float(self.v[i])

    def interpolated(self, t_ns: int) -> float | None:
        """Linear interpolation; the last value after the end; None before the first sample."""
        if len(self.t) == 0 or t_ns < self.t[0]:
            return None
        # Relative times: float64 cannot hold epoch nanoseconds exactly (256 ns steps).
        t0 = int(self.t[0])
        return float(np.interp(float(t_ns - t0), (self.t - t0).astype(np.float64), self.v))


class FrameReader:
    """Iterate the observation frames of a log (see the module docstring).

    ``tf_tolerance_ns`` lets TF lookups hold the end pose of a dynamic transform that
    far past its data; ``max_latency_ns`` bounds how long an incomplete frame waits for
    a late sensor; ``start_ns``/``end_ns`` keep only frames whose time (stamp) lies in
    that interval (inclusive).
    Frames (or sensors) at times without TF data are skipped and listed in
    ``skipped`` as ``(stamp_ns, reason)``; unknown or unconnected TF frames raise
    LogError.
    """

    def __init__(
        self,
        log: McapLog,
        sensors: Sequence[SensorTopics],
        topics: LogTopics = LogTopics(),
        *,
        tf_tolerance_ns: int = 0,
        max_latency_ns: int = 250_000_000,
        max_pending: int = 64,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ):
        if not sensors:
            raise ValueError("FrameReader needs at least one sensor")
        names = [s.name for s in sensors]
        if len(set(names)) != len(names):
            raise ValueError(f"sensor names must be unique: {names}")
        self.log = log
        self.sensors = tuple(sensors)
        self.topics = topics
        self.tf_tolerance_ns = tf_tolerance_ns
        self.max_latency_ns = max_latency_ns
        self.max_pending = max_pending
        self.start_ns, self.end_ns = start_ns, end_ns
        self.skipped: list[tuple[int, str]] = []
        self._undistort_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self.tf = TfBuffer(tf_tolerance_ns, source=str(log.path))
        self._summary = log.summary()
        self._check_topics()
        self._loaded = False

    # --- topic checks ---------------------------------------------------------------------

    def _type_of(self, topic: str | None) -> str | None:
        if topic is None or not self._summary.has_topic(topic):
            return None
        return rm.normalize_type(self._summary.topic(topic).type)

    def _require(self, topic: str, allowed: tuple[str, ...], what: str, optional: bool = False) -> bool:
        actual = self._type_of(topic)
        if actual is None:
            if optional:
                return False
            raise LogError(f"{self.log.path}: topic {topic!r} not found (expected {' or '.join(allowed)} for {what})")
        if actual not in allowed:
            raise LogError(
                f"{self.log.path}: topic {topic!r} has type {actual!r} (expected {' or '.join(allowed)} for {what})"
            )
        return True

    def _check_topics(self) -> None:
        t = self.topics
        self._has_tf = self._require(t.tf, (rm.TF_MESSAGE,), "TF", optional=True)
        self._has_tf_static = self._require(t.tf_static, (rm.TF_MESSAGE,), "static TF", optional=True)
        if not (self._has_tf or self._has_tf_static):
            raise LogError(
                f"{self.log.path}: neither {t.tf!r} nor {t.tf_static!r} is in the log "
                "(expected tf2_msgs/msg/TFMessage transforms)"
            )
        self._has_contact = t.contact is not None and self._require(t.contact, (rm.BOOL,), "contact", optional=True)
        self._has_wrench = (
            not self._has_contact and t.wrench is not None
            and self._require(t.wrench, (rm.WRENCH_STAMPED,), "contact from force", optional=True)
        )
        if self._has_wrench and not t.contact_force_on_n > t.contact_force_off_n >= 0:
            raise ValueError(
                f"contact force thresholds need on > off >= 0, got {t.contact_force_on_n}, {t.contact_force_off_n}"
            )
        self._has_joints = t.joint_states is not None and self._require(
            t.joint_states, (rm.JOINT_STATE,), "finger opening", optional=True
        )
        self._has_gt = t.ground_truth is not None and self._require(
            t.ground_truth, (rm.POSE_STAMPED,), "ground truth", optional=True
        )
        self._depth_topics: dict[str, str] = {}
        for s in self.sensors:
            self._require(s.image_topic, (rm.IMAGE, rm.COMPRESSED_IMAGE), f"{s.modality} {s.name!r}")
            self._require(s.info_topic, (rm.CAMERA_INFO,), f"{s.modality} {s.name!r}")
            if s.depth_topic and self._require(s.depth_topic, (rm.IMAGE,), f"depth of {s.name!r}", optional=True):
                self._depth_topics[s.name] = s.depth_topic
        self._mask_topics: dict[str, str] = {}
        for s in self.sensors:
            if s.mask_topic:
                self._require(s.mask_topic, (rm.IMAGE, rm.COMPRESSED_IMAGE), f"the object masks of {s.name!r}")
                if self._summary.topic(s.mask_topic).message_count == 0:
                    raise LogError(f"{self.log.path}: topic {s.mask_topic!r} has no messages "
                                   f"(expected the object masks of {s.modality} {s.name!r})")
                self._mask_topics[s.name] = s.mask_topic

    # --- pass 1: small topics ---------------------------------------------------------------

    def _load_context(self) -> None:
        t = self.topics
        small: list[str] = []
        if self._has_tf:
            small.append(t.tf)
        if self._has_tf_static:
            small.append(t.tf_static)
        if self._has_contact:
            small.append(t.contact)  # type: ignore[arg-type]
        if self._has_wrench:
            small.append(t.wrench)  # type: ignore[arg-type]
        if self._has_joints:
            small.append(t.joint_states)  # type: ignore[arg-type]
        if self._has_gt:
            small.append(t.ground_truth)  # type: ignore[arg-type]
        info_of: dict[str, list[str]] = {}
        for s in self.sensors:
            info_of.setdefault(s.info_topic, []).append(s.name)
        small.extend(info_of)

        self._contact = _Series()
        touching = False  # hysteresis state of a force-based contact signal
        js_t: list[int] = []
        js_names: list[list[str]] = []
        js_pos: list[list[float]] = []
        self._finger = _Series()
        gt_t: list[int] = []
        gt_v: list[np.ndarray] = []
        self._gt_frame: str | None = None
        # per sensor: stamps and cameras where the calibration changed, plus the frame id
        self._infos: dict[str, tuple[list[int], list[PinholeCamera]]] = {s.name: ([], []) for s in self.sensors}
        self._info_frame: dict[str, str] = {}

        for m in self.log.messages(sorted(set(small))):
            msg = m.msg
            if m.topic == t.tf_static and self._has_tf_static:
                self.tf.add_tf_message(msg, static=True)
            elif m.topic == t.tf and self._has_tf:
                self.tf.add_tf_message(msg, static=False)
            elif m.topic == t.contact:
                self._contact.add(m.log_time_ns, float(bool(msg.data)))
            elif self._has_wrench and m.topic == t.wrench:
                f = msg.wrench.force
                force = float(np.sqrt(f.x * f.x + f.y * f.y + f.z * f.z))
                if force >= t.contact_force_on_n:
                    touching = True
                elif force <= t.contact_force_off_n:
                    touching = False
                self._contact.add(header_stamp_ns(msg, m.log_time_ns), float(touching))
            elif m.topic == t.joint_states:
                if t.urdf is not None:
                    js_t.append(header_stamp_ns(msg, m.log_time_ns))
                    js_names.append([str(n) for n in msg.name])
                    js_pos.append([float(v) for v in msg.position])
                # JointState may leave position empty (names only): zip stops at the shorter.
                fingers = [p for n, p in zip(msg.name, msg.position) if "finger" in n.lower()]
                if fingers:
                    self._finger.add(header_stamp_ns(msg, m.log_time_ns), float(sum(fingers)))
            elif m.topic == t.ground_truth:
                frame = str(msg.header.frame_id).lstrip("/")
                if self._gt_frame is None:
                    self._gt_frame = frame
                elif frame != self._gt_frame:
                    raise LogError(
                        f"{self.log.path}: ground truth on {t.ground_truth!r} changes frame from "
                        f"{self._gt_frame!r} to {frame!r} at log time {m.log_time_ns} ns (expected one frame)"
                    )
                p, q = msg.pose.position, msg.pose.orientation
                tr, quat = valid_transform(
                    (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), str(self.log.path),
                    f"ground truth on {t.ground_truth!r} at log time {m.log_time_ns} ns",
                )
                gt_t.append(header_stamp_ns(msg, m.log_time_ns))
                gt_v.append(np.array([*tr, *quat]))
            if m.topic in info_of:
                try:
                    cam = camera_from_info(msg, m.topic)
                except LogError as err:  # the parser knows the topic; add the log and time
                    raise LogError(f"{self.log.path}: {err} (log time {m.log_time_ns} ns)") from err
                for name in info_of[m.topic]:
                    stamps, cams = self._infos[name]
                    if not cams or not _same_camera(cams[-1], cam):
                        stamps.append(header_stamp_ns(msg, m.log_time_ns))
                        cams.append(cam)
                    if msg.header.frame_id:
                        self._info_frame.setdefault(name, str(msg.header.frame_id).lstrip("/"))
        self._contact.finish()
        self._finger.finish()
        if t.urdf is not None:
            if not js_t:
                raise LogError(f"{self.log.path}: a URDF is configured but {t.joint_states!r} has no joint states")
            from .urdf import UrdfKinematics

            kin = UrdfKinematics(t.urdf)
            known = {f for f in self.tf.frames if self.tf.parent(f) is not None}
            kin.add_to_tf(self.tf, js_t, js_names, js_pos, skip=known)
        self._gt: PoseSeries | None = None
        if gt_t:
            v = np.stack(gt_v)
            self._gt = PoseSeries(np.asarray(gt_t, dtype=np.int64), v[:, :3], v[:, 3:])
        for s in self.sensors:
            if not self._infos[s.name][1]:
                raise LogError(
                    f"{self.log.path}: topic {s.info_topic!r} has no messages "
                    f"(expected sensor_msgs/msg/CameraInfo for {s.modality} {s.name!r})"
                )
        # Fail early (not at the first frame) when the world or ee frame is not in TF.
        self.tf.time_bounds(t.world_frame, t.ee_frame)
        self._loaded = True

    def _undistort(self, name: str, rgb: np.ndarray, depth, camera: PinholeCamera, stamp: int, mask=None):
        """The image (and depth) undistorted to the pinhole model the renderers use, that
        camera without distortion, and the recorded mask undistorted (nearest label); the remap
        tables are cached per sensor and calibration."""
        import cv2

        key = (name, camera.width, camera.height, camera.K.tobytes(), np.asarray(camera.distortion).tobytes())
        maps = self._undistort_cache.get(key)
        if maps is None:
            maps = self._undistort_cache[key] = undistort_maps(camera)
        if rgb.shape[:2] != (camera.height, camera.width):
            raise LogError(
                f"{self.log.path}: sensor {name!r}: image of {rgb.shape[1]}x{rgb.shape[0]} px but CameraInfo "
                f"says {camera.width}x{camera.height} (stamp {stamp} ns)"
            )
        rgb = cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        if depth is not None:
            depth = cv2.remap(depth, maps[0], maps[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        if mask is not None:
            mask = cv2.remap(mask, maps[0], maps[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        pinhole = PinholeCamera(width=camera.width, height=camera.height, K=camera.K,
                                distortion_model=camera.distortion_model,
                                distortion=np.zeros_like(np.asarray(camera.distortion, dtype=np.float64)))
        return rgb, depth, pinhole, mask

    def _camera_at(self, sensor: str, t_ns: int) -> PinholeCamera:
        stamps, cams = self._infos[sensor]
        i = int(np.searchsorted(np.asarray(stamps), t_ns, side="right")) - 1
        return cams[max(i, 0)]

    def load(self) -> None:
        """Read TF, contact, joint states, ground truth and calibrations (pass 1) now
        instead of at the first frame; the accessors below need it."""
        if not self._loaded:
            self._load_context()

    def ground_truth_at(self, t_ns: int) -> np.ndarray | None:
        """Ground-truth ``T_world_object`` (4, 4) at ``t_ns``, interpolated and converted
        from the ground truth's own frame into the world frame through TF (the same as the
        frames' ``T_world_object_gt``); None where the messages (within the sync tolerance)
        or TF do not cover ``t_ns``."""
        self.load()
        return self._gt_at(int(t_ns))

    def contact_at(self, t_ns: int) -> bool | None:
        """The log's contact state at ``t_ns`` as the frames read it (the contact topic's latest
        message, or the force with hysteresis); None without a contact signal or before its
        first message."""
        self.load()
        if not (self._has_contact or self._has_wrench):
            return None
        v = self._contact.latest(int(t_ns))
        return None if v is None else bool(v)

    @property
    def ground_truth_frame(self) -> str | None:
        """``header.frame_id`` of the ground-truth messages (None without any)."""
        self.load()
        return self._gt_frame

    def camera_at(self, sensor: str, t_ns: int) -> PinholeCamera:
        """The calibration of ``sensor`` in force at ``t_ns``, as the log recorded it."""
        self.load()
        return self._camera_at(sensor, int(t_ns))

    def sensor_frame(self, sensor: str) -> str | None:
        """The TF frame of ``sensor``'s images: the configured one, else its CameraInfo's."""
        self.load()
        s = next(s for s in self.sensors if s.name == sensor)
        return s.frame_id or self._info_frame.get(sensor)

    def _gt_at(self, t_ns: int) -> np.ndarray | None:
        gt = self._gt
        if gt is None or not gt.covers(t_ns, self.topics.sync_tolerance_ns):
            return None
        T = gt.at(t_ns)
        frame = self._gt_frame or self.topics.world_frame
        if frame != self.topics.world_frame:
            lo, hi = self.tf.time_bounds(self.topics.world_frame, frame)
            if not lo <= t_ns <= hi:
                return None
            T = self.tf.lookup(self.topics.world_frame, frame, t_ns) @ T
        return T

    # --- pass 2: images -----------------------------------------------------------------------

    def __iter__(self) -> Iterator[Frame]:
        if not self._loaded:
            self._load_context()
        t = self.topics
        tol = int(t.sync_tolerance_ns)
        keys_of: dict[str, list[tuple[str, str]]] = {}
        for s in self.sensors:
            keys_of.setdefault(s.image_topic, []).append((s.name, "image"))
            if s.name in self._depth_topics:
                keys_of.setdefault(self._depth_topics[s.name], []).append((s.name, "depth"))
            if s.name in self._mask_topics:
                keys_of.setdefault(self._mask_topics[s.name], []).append((s.name, "mask"))
        complete_keys = set(k for ks in keys_of.values() for k in ks)

        pending: list[_Group] = []  # sorted by .lo
        recent: deque[_Group] = deque(maxlen=8)  # last emitted groups, to recognise late images
        newest = None
        last_emitted: int | None = None
        index = 0
        # Read by log time from a little before the window (stamps precede log times) to
        # the latency horizon after it; frames are then kept by their stamp.
        read_from = None if self.start_ns is None else self.start_ns - tol
        read_to = None if self.end_ns is None else self.end_ns + tol + self.max_latency_ns

        def emit_ready(final: bool) -> Iterator[Frame]:
            nonlocal index, last_emitted
            while pending:
                g = pending[0]
                ready = (
                    final
                    or set(g.slots) >= complete_keys
                    or (newest is not None and newest - g.lo > tol + self.max_latency_ns)
                    or len(pending) > self.max_pending
                )
                if not ready:
                    return
                pending.pop(0)
                recent.append(g)
                if not self._in_window(g):
                    continue
                frame = self._build(g, index)
                if frame is not None:
                    last_emitted = frame.stamp_ns
                    index += 1
                    yield frame

        for m in self.log.messages(sorted(keys_of), read_from, read_to):
            stamp = header_stamp_ns(m.msg, m.log_time_ns)
            newest = stamp if newest is None else max(newest, stamp)
            for key in keys_of[m.topic]:
                candidates = [g for g in pending if g.fits(key, stamp, tol)]
                if candidates:
                    g = min(candidates, key=lambda g: abs((g.lo + g.hi) / 2 - stamp))
                    g.add(key, stamp, m)
                    continue
                late = any(g.fits(key, stamp, tol) for g in recent)
                if late or (last_emitted is not None and stamp < last_emitted):
                    self.skipped.append(
                        (stamp, f"{m.topic}: arrived after its frame was emitted (latency > {self.max_latency_ns} ns)")
                    )
                    continue
                g = _Group()
                g.add(key, stamp, m)
                pos = next((i for i, other in enumerate(pending) if other.lo > g.lo), len(pending))
                pending.insert(pos, g)
            yield from emit_ready(final=False)
        yield from emit_ready(final=True)

    def _in_window(self, g: _Group) -> bool:
        stamps = [st for (_name, kind), (st, _m) in g.slots.items() if kind == "image"] or [g.lo]
        t = min(stamps)
        return (self.start_ns is None or t >= self.start_ns) and (self.end_ns is None or t <= self.end_ns)

    def _build(self, g: _Group, index: int) -> Frame | None:
        t = self.topics
        tol_ns = int(t.sync_tolerance_ns)
        image_stamps = [st for (name, kind), (st, _m) in g.slots.items() if kind == "image"]
        if not image_stamps:
            self.skipped.append((g.lo, "depth or mask without an image in the same frame"))
            return None
        stamp = min(image_stamps)
        lo, hi = self.tf.time_bounds(t.world_frame, t.ee_frame)
        if not lo <= stamp <= hi:
            self.skipped.append((stamp, f"no TF for {t.world_frame} -> {t.ee_frame} at this time"))
            return None
        T_world_ee = self.tf.lookup(t.world_frame, t.ee_frame, stamp)
        cameras: dict[str, SensorImage] = {}
        tactile: dict[str, SensorImage] = {}
        for s in self.sensors:
            slot = g.slots.get((s.name, "image"))
            if slot is None:
                continue
            st, m = slot
            frame_id = s.frame_id or self._info_frame.get(s.name) or str(m.msg.header.frame_id).lstrip("/")
            if not frame_id:
                raise LogError(
                    f"{self.log.path}: no TF frame for {s.modality} {s.name!r} (CameraInfo and image headers "
                    "have an empty frame_id; expected one, or frame_id in the sensor description)"
                )
            slo, shi = self.tf.time_bounds(t.world_frame, frame_id)
            if not slo <= st <= shi:
                self.skipped.append((st, f"{s.name}: no TF for {t.world_frame} -> {frame_id} at this time"))
                continue
            if not lo <= st <= hi:
                self.skipped.append((st, f"{s.name}: no TF for {t.world_frame} -> {t.ee_frame} at this time"))
                continue
            depth = mask = None
            dslot = g.slots.get((s.name, "depth"))
            mslot = g.slots.get((s.name, "mask"))
            if s.name in self._mask_topics and mslot is None:
                self.skipped.append((st, f"{s.name}: no mask on {self._mask_topics[s.name]!r} within the sync "
                                         f"tolerance of {tol_ns} ns"))
                continue
            camera = self._camera_at(s.name, st)
            size = (camera.width, camera.height)
            try:
                if dslot is not None:
                    depth = decode_depth(dslot[1].msg, dslot[1].topic, size)
                if mslot is not None:
                    mask = decode_mask(mslot[1].msg, mslot[1].topic, size)
                rgb = decode_image(m.msg, m.topic, size)
            except LogError as err:  # the decoders know the topic; add the log and time
                raise LogError(f"{self.log.path}: {err} (stamp {st} ns)") from err
            if camera.has_distortion:
                rgb, depth, camera, mask = self._undistort(s.name, rgb, depth, camera, st, mask)
            img = SensorImage(
                sensor=s.name,
                stamp_ns=st,
                image=rgb,
                camera=camera,
                T_world_sensor=self.tf.lookup(t.world_frame, frame_id, st),
                depth=depth,
                T_world_ee=T_world_ee if st == stamp else self.tf.lookup(t.world_frame, t.ee_frame, st),
                mask=mask,
            )
            (cameras if s.modality == "camera" else tactile)[s.name] = img
        if not cameras and not tactile:
            self.skipped.append((stamp, "no sensor of the frame is usable (TF or recorded mask missing)"))
            return None
        contact = self.contact_at(stamp)
        return Frame(
            index=index,
            stamp_ns=stamp,
            T_world_ee=T_world_ee,
            cameras=cameras,
            tactile=tactile,
            contact=contact,
            finger_opening_m=self._finger.interpolated(stamp) if self._has_joints else None,
            T_world_object_gt=self._gt_at(stamp),
        )


def _same_camera(a: PinholeCamera, b: PinholeCamera) -> bool:
    return (
        a.width == b.width
        and a.height == b.height
        and a.distortion_model == b.distortion_model
        and np.array_equal(a.K, b.K)
        and np.array_equal(np.asarray(a.distortion), np.asarray(b.distortion))
    )


def iter_frames(
    log: McapLog | str | Path,
    sensors: Sequence[SensorTopics],
    topics: LogTopics = LogTopics(),
    **options: Any,
) -> Iterator[Frame]:
    """Frames of ``log`` (an open McapLog, or a path opened and closed here); ``options``
    go to FrameReader."""
    if isinstance(log, McapLog):
        yield from FrameReader(log, sensors, topics, **options)
        return
    with McapLog(log) as opened:
        yield from FrameReader(opened, sensors, topics, **options)


__all__ = [
    "FrameReader",
    "LogTopics",
    "SensorTopics",
    "camera_from_info",
    "header_stamp_ns",
    "iter_frames",
]
