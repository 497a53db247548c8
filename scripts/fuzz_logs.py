#!/usr/bin/env python3
"""Fuzz the log reader: feed mutated MCAP logs through ``mvtop inspect`` and ``mvtop estimate``.

    .venv/bin/python scripts/fuzz_logs.py --count 10000 --seed 0

Every input is a small log written from a base scene (3 frames; a raw and a compressed
camera of 32 x 24 px, two 20 x 16 px tactile sensors with depth; TF, contact, wrench,
joint states and ground truth) and then mutated:

- at the message level, re-encoded through the writer: wrong image sizes (width * height
  * channels != data length), encodings and steps, bad or foreign compressed bytes, bad
  CameraInfo, NaN/inf and broken trees in TF, non-monotonic or out-of-range stamps,
  truncated or padded CDR, corrupt schemas and encodings, missing or duplicated messages;
- at the byte level, on one of several layouts (zstd, lz4 or uncompressed chunks,
  unchunked messages, no index): bit flips, byte overwrites, truncations, inserted or
  deleted bytes, wrong record lengths, and chunk contents changed with the chunk CRC
  recomputed or zeroed (so the decoders, not the CRC check, see the bad bytes).

Each command must end in one of these outcomes:

  ok       exit 0 (estimate: all four output files, no temporary file left)
  skipped  exit 0 with frames skipped and counted in summary.json (a documented skip)
  error    exit 2 with one line ``mvtop: error: ...`` naming the log, and no output file

Anything else is a failure: ``crash`` (any other exception: a traceback), ``hang`` (over
``--timeout`` seconds of CPU time, or five times that of wall time), ``died`` (the process
was killed, e.g. by a signal), ``unclear`` (exit 2 without that one line), ``partial`` (a
failed run left an output file), ``noisy`` (a successful run printed something other than
``mvtop: warning:`` lines and the plain progress lines a run longer than a minute prints off
a terminal, ``PROGRESS_LINE``). The script prints the counts per command and outcome, the
time taken and the most frequent kinds of error; for each distinct failure it keeps the
smallest input, simplifies it while it still fails (``Spec.smaller``), writes it to
``--keep`` with its description and traceback, and exits 1. The commands run in a worker
process (address space capped at 6 GB) that is killed and restarted when an input exceeds
the time limit. See docs/robustness.md; tests/io/test_fuzz_logs.py runs a small
deterministic part in CI.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import select
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from mcap.writer import CompressionType, IndexType  # noqa: E402
from mcap.writer import Writer as McapWriter  # noqa: E402

from mvtop_cli.geometry import se3  # noqa: E402
from mvtop_cli.io import ros2_msgs as rm  # noqa: E402
from mvtop_cli.io.images import encode_compressed, encode_raw  # noqa: E402
from mvtop_cli.io.mcap_writer import _Cdr  # noqa: E402

COMMANDS = ("inspect", "estimate")
GOOD = ("ok", "skipped", "error")
FAILURES = ("crash", "hang", "died", "unclear", "partial", "noisy")
OUTPUT_FILES = ("track.mcap", "track.csv", "summary.json", "config.resolved.yaml")
# The plain progress line of a long run on stderr (``cli._progress``), e.g.
# ``estimate base.mcap: 12/30 (40 %), 1 min 2 s elapsed, about 1 min 30 s left``.
PROGRESS_LINE = re.compile(r"^[a-z][\w -]* [^:]+: \d+/\d+ \(\d+ %\), .+ elapsed(, about .+ left)?$")

# --- the base scene ------------------------------------------------------------------------

T0 = 1_700_000_000_000_000_000  # epoch stamp of the first frame [ns]
MS = 1_000_000
N_FRAMES = 3
FRAME_PERIOD_NS = 100 * MS
CAM_W, CAM_H = 32, 24
TAC_W, TAC_H = 20, 16
K_CAM = [40.0, 0.0, 15.5, 0.0, 40.0, 11.5, 0.0, 0.0, 1.0]
K_TAC = [30.0, 0.0, 9.5, 0.0, 30.0, 7.5, 0.0, 0.0, 1.0]

_CUBE_OBJ = """\
# 10 mm cube, metres
v -0.005 -0.005 0.0
v 0.005 -0.005 0.0
v 0.005 0.005 0.0
v -0.005 0.005 0.0
v -0.005 -0.005 0.01
v 0.005 -0.005 0.01
v 0.005 0.005 0.01
v -0.005 0.005 0.01
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 2 3 7
f 2 7 6
f 3 4 8
f 3 8 7
f 4 1 5
f 4 5 8
"""


def _box_obj(sx: float, sy: float, sz: float) -> str:
    lines = ["# box, metres"]
    for z in (0.0, sz):
        for x, y in ((-sx, -sy), (sx, -sy), (sx, sy), (-sx, sy)):
            lines.append(f"v {x / 2} {y / 2} {z}")
    lines += _CUBE_OBJ.splitlines()[9:]
    return "\n".join(lines) + "\n"


CONFIG_YAML = """\
# Tiny scene for fuzzing the log reader (scripts/fuzz_logs.py): cheap to estimate.
object: {name: cube, mesh: cube.obj, units: m, clearance_m: 0.0003}
environment:
  - {name: plate, mesh: plate.obj, frame: world, pose: {xyz_m: [0.0, 0.0, -0.006]}}
  - {name: finger, mesh: finger.obj, frame: finger_left, collide: false}
sensors:
  cameras:
    - {name: front, image_topic: /cameras/front/image, info_topic: /cameras/front/camera_info}
    - {name: side, image_topic: /cameras/side/image/compressed, info_topic: /cameras/side/camera_info,
       frame: side_optical}
  tactile:
    - {name: left, image_topic: /tactile/left/image/compressed, info_topic: /tactile/left/camera_info,
       depth_topic: /tactile/left/depth, frame: tactile_left_optical, gel_distance_m: 0.02}
    - {name: right, image_topic: /tactile/right/image, info_topic: /tactile/right/camera_info,
       depth_topic: /tactile/right/depth, gel_distance_m: 0.02}
topics: {wrench: /wrench}
grasp_prior: {pose: {xyz_m: [0.0, 0.0, 0.0]}, translation_m: 0.002, rotation_deg: 5.0}
filter: {num_particles: 10, refine_iterations: 1, roi_size_px: 16, seed: 0}
contact: {sdf_resolution_m: 0.002}
"""


def write_config(folder: Path) -> Path:
    """The tiny scene's meshes and config in ``folder``; returns the config path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cube.obj").write_text(_CUBE_OBJ)
    (folder / "plate.obj").write_text(_box_obj(0.04, 0.04, 0.005))
    (folder / "finger.obj").write_text(_box_obj(0.01, 0.004, 0.03))
    path = folder / "fuzz.yaml"
    path.write_text(CONFIG_YAML)
    return path


@dataclass
class Event:
    """One message of a log: ``fields`` are encoded by ``encode``; ``raw`` (CDR bytes) overrides them."""

    log_time: int
    topic: str
    type: str
    fields: dict
    raw: bytes | None = None


@dataclass
class Scene:
    """A log to write: its messages and per-topic channel overrides (``schema_name``,
    ``schema_text``, ``schema_encoding``, ``message_encoding``, ``topic``)."""

    events: list[Event]
    channels: dict[str, dict] = field(default_factory=dict)


def _header(stamp_ns: int, frame_id: str) -> dict:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec, "frame_id": frame_id}


def _look_at(eye, target) -> np.ndarray:
    """T_world_cam of an optical frame (z forward, y down) at ``eye`` looking at ``target``."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, -1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return se3.make_pose(np.stack([x, y, z], axis=1), eye)


def _tf(parent: str, child: str, T: np.ndarray, stamp_ns: int) -> dict:
    return {"header": _header(stamp_ns, parent), "child": child,
            "t": [float(v) for v in T[:3, 3]], "q": [float(v) for v in se3.to_quat_xyzw(T)]}


def _pose_fields(T: np.ndarray, stamp_ns: int, frame: str) -> dict:
    return {"header": _header(stamp_ns, frame), "t": [float(v) for v in T[:3, 3]],
            "q": [float(v) for v in se3.to_quat_xyzw(T)]}


def _image(seed: int, h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(40, 90, (h, w, 3), dtype=np.uint8)
    img[h // 3 : 2 * h // 3, w // 3 : 2 * w // 3] = (200, 60, 40)  # the "object"
    return img


def _camera_info(stamp_ns: int, frame: str, w: int, h: int, k: list[float], d: list[float]) -> dict:
    P = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]
    return {"header": _header(stamp_ns, frame), "height": h, "width": w, "distortion_model": "plumb_bob",
            "d": list(d), "k": list(k), "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "p": P}


def base_scene() -> Scene:
    """The unmutated log: 3 frames at 10 Hz, every sensor at every frame."""
    ev: list[Event] = []
    T_world_front = _look_at([0.0, -0.15, 0.05], [0.0, 0.0, 0.01])
    T_world_side = _look_at([0.15, 0.0, 0.05], [0.0, 0.0, 0.01])
    T_ee_left = se3.make_pose(se3.rotvec_to_matrix(np.array([-np.pi / 2, 0.0, 0.0])), [0.0, 0.012, 0.005])
    T_ee_right = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi / 2, 0.0, 0.0])), [0.0, -0.012, 0.005])
    T_ee_finger = se3.make_pose(np.eye(3), [0.0, 0.016, -0.01])
    static = [_tf("world", "front_optical", T_world_front, T0), _tf("world", "side_optical", T_world_side, T0),
              _tf("ee", "tactile_left_optical", T_ee_left, T0), _tf("ee", "tactile_right_optical", T_ee_right, T0),
              _tf("ee", "finger_left", T_ee_finger, T0)]
    ev.append(Event(T0 - 100 * MS, "/tf_static", rm.TF_MESSAGE, {"transforms": static}))
    T_ee_obj = np.eye(4)
    for i in range(N_FRAMES + 2):  # TF and the small topics from one period before to one after
        t = T0 + (i - 1) * FRAME_PERIOD_NS
        T_world_ee = se3.make_pose(np.eye(3), [0.0, 0.0, 0.004 - 0.002 * i])
        ev.append(Event(t, "/tf", rm.TF_MESSAGE, {"transforms": [_tf("world", "ee", T_world_ee, t)]}))
        ev.append(Event(t, "/contact", rm.BOOL, {"data": int(i >= 2)}))
        ev.append(Event(t, "/wrench", rm.WRENCH_STAMPED,
                        {"header": _header(t, "ee"), "force": [0.0, 0.0, -3.0 * (i >= 2)], "torque": [0.0, 0.0, 0.0]}))
        ev.append(Event(t, "/joint_states", rm.JOINT_STATE,
                        {"header": _header(t, ""), "name": ["finger_joint1", "finger_joint2"],
                         "position": [0.005, 0.005], "velocity": [], "effort": []}))
        ev.append(Event(t, "/ground_truth/object_pose", rm.POSE_STAMPED,
                        _pose_fields(T_world_ee @ T_ee_obj, t, "world")))
    for k in range(N_FRAMES):
        st = T0 + k * FRAME_PERIOD_NS
        lt = st + 3 * MS
        raw = encode_raw(_image(10 + k, CAM_H, CAM_W), "rgb8")
        ev.append(Event(lt, "/cameras/front/image", rm.IMAGE, {"header": _header(st, "front_optical"), **raw}))
        ev.append(Event(lt, "/cameras/front/camera_info", rm.CAMERA_INFO,
                        _camera_info(st, "front_optical", CAM_W, CAM_H, K_CAM, [0.0] * 5)))
        png = encode_compressed(_image(20 + k, CAM_H, CAM_W), "png")
        ev.append(Event(lt + MS, "/cameras/side/image/compressed", rm.COMPRESSED_IMAGE,
                        {"header": _header(st + MS, "side_optical"), **png}))
        ev.append(Event(lt + MS, "/cameras/side/camera_info", rm.CAMERA_INFO,
                        _camera_info(st + MS, "side_optical", CAM_W, CAM_H, K_CAM, [-0.05, 0.01, 0.0, 0.0, 0.0])))
        jpg = encode_compressed(_image(30 + k, TAC_H, TAC_W), "jpeg", 90)
        ev.append(Event(lt + 2 * MS, "/tactile/left/image/compressed", rm.COMPRESSED_IMAGE,
                        {"header": _header(st, "tactile_left_optical"), **jpg}))
        depth = np.zeros((TAC_H, TAC_W), np.float32)
        depth[5:11, 6:14] = 5e-5 * k
        ev.append(Event(lt + 2 * MS, "/tactile/left/depth", rm.IMAGE,
                        {"header": _header(st, "tactile_left_optical"), **encode_raw(depth, "32FC1")}))
        ev.append(Event(lt + 2 * MS, "/tactile/left/camera_info", rm.CAMERA_INFO,
                        _camera_info(st, "tactile_left_optical", TAC_W, TAC_H, K_TAC, [])))
        ev.append(Event(lt + 2 * MS, "/tactile/right/image", rm.IMAGE,
                        {"header": _header(st, "tactile_right_optical"),
                         **encode_raw(_image(40 + k, TAC_H, TAC_W), "bgr8")}))
        ev.append(Event(lt + 2 * MS, "/tactile/right/depth", rm.IMAGE,
                        {"header": _header(st, "tactile_right_optical"), **encode_raw(depth, "16UC1")}))
        ev.append(Event(lt + 2 * MS, "/tactile/right/camera_info", rm.CAMERA_INFO,
                        _camera_info(st, "tactile_right_optical", TAC_W, TAC_H, K_TAC, [0.0] * 5)))
    ev.sort(key=lambda e: e.log_time)
    return Scene(ev)


# --- CDR encoding that tolerates bad values -------------------------------------------------


def _u32(v: Any) -> int:
    return int(v) & 0xFFFFFFFF


def _f64s(c: _Cdr, values: Any, fixed: bool) -> None:
    """float64 values: a sequence (length prefix) or a fixed array (no prefix, any count)."""
    arr = np.asarray(values, dtype="<f8").ravel()
    if not fixed:
        c.u32(len(arr))
    if len(arr):
        c._align(8)
        c.buf += arr.tobytes()


def _enc_header(c: _Cdr, h: dict) -> None:
    c.i32(int(h["sec"]))
    c.u32(_u32(h["nanosec"]))
    c.string(h["frame_id"])


def encode(type_name: str, f: dict) -> bytes:
    """CDR bytes of a message of ``type_name`` from ``fields`` (any values, even invalid ones)."""
    c = _Cdr()
    if type_name == rm.TF_MESSAGE:
        c.u32(len(f["transforms"]))
        for tr in f["transforms"]:
            _enc_header(c, tr["header"])
            c.string(tr["child"])
            for v in (*tr["t"], *tr["q"]):
                c.f64(v)
    elif type_name == rm.IMAGE:
        _enc_header(c, f["header"])
        c.u32(_u32(f["height"]))
        c.u32(_u32(f["width"]))
        c.string(f["encoding"])
        c.u8(f["is_bigendian"])
        c.u32(_u32(f["step"]))
        c.byte_seq(bytes(f["data"]))
    elif type_name == rm.COMPRESSED_IMAGE:
        _enc_header(c, f["header"])
        c.string(f["format"])
        c.byte_seq(bytes(f["data"]))
    elif type_name == rm.CAMERA_INFO:
        _enc_header(c, f["header"])
        c.u32(_u32(f["height"]))
        c.u32(_u32(f["width"]))
        c.string(f["distortion_model"])
        _f64s(c, f["d"], fixed=False)
        _f64s(c, f["k"], fixed=True)
        _f64s(c, f["r"], fixed=True)
        _f64s(c, f["p"], fixed=True)
        for _ in range(6):  # binning_x, binning_y, roi x_offset, y_offset, height, width
            c.u32(0)
        c.boolean(False)
    elif type_name == rm.BOOL:
        c.u8(f["data"])
    elif type_name == rm.WRENCH_STAMPED:
        _enc_header(c, f["header"])
        for v in (*f["force"], *f["torque"]):
            c.f64(v)
    elif type_name == rm.JOINT_STATE:
        _enc_header(c, f["header"])
        c.strings(list(f["name"]))
        for key in ("position", "velocity", "effort"):
            _f64s(c, f[key], fixed=False)
    elif type_name == rm.POSE_STAMPED:
        _enc_header(c, f["header"])
        for v in (*f["t"], *f["q"]):
            c.f64(v)
    else:
        raise ValueError(f"no encoder for {type_name}")
    return bytes(c.buf)


# --- writing a scene in one of several file layouts ----------------------------------------

LAYOUTS = ("zstd", "lz4", "none", "small_chunks", "unchunked", "no_index", "no_summary_offsets")


def write_scene(scene: Scene, layout: str = "zstd") -> bytes:
    """The MCAP bytes of ``scene`` in ``layout`` (chunk compression, chunking, indexes)."""
    kw: dict[str, Any] = {"compression": CompressionType.ZSTD, "chunk_size": 1 << 20}
    if layout == "lz4":
        kw["compression"] = CompressionType.LZ4
    elif layout in ("none", "no_index", "no_summary_offsets"):
        kw["compression"] = CompressionType.NONE
    elif layout == "small_chunks":
        kw.update(compression=CompressionType.NONE, chunk_size=4096)
    elif layout == "unchunked":
        kw["use_chunking"] = False
    if layout == "no_index":
        kw.update(index_types=IndexType.NONE, use_statistics=False)
    if layout == "no_summary_offsets":
        kw.update(use_summary_offsets=False, chunk_size=8192)
    buf = io.BytesIO()
    w = McapWriter(buf, enable_crcs=True, **kw)
    w.start(profile="ros2", library="mvtop-fuzz")
    schema_ids: dict[tuple, int] = {}
    channel_ids: dict[str, int] = {}
    for e in scene.events:
        cid = channel_ids.get(e.topic)
        if cid is None:
            o = scene.channels.get(e.topic, {})
            name = o.get("schema_name", e.type)
            text = o.get("schema_text", rm.definition(e.type) if e.type in rm.MESSAGE_TYPES else "")
            key = (name, o.get("schema_encoding", "ros2msg"), text)
            sid = schema_ids.get(key)
            if sid is None:
                sid = schema_ids[key] = w.register_schema(name, key[1], text.encode())
            cid = channel_ids[e.topic] = w.register_channel(
                o.get("topic", e.topic), o.get("message_encoding", "cdr"), sid
            )
        data = e.raw if e.raw is not None else encode(e.type, e.fields)
        w.add_message(channel_id=cid, log_time=e.log_time, publish_time=e.log_time, data=data)
    w.finish()
    return buf.getvalue()


# --- message-level mutations ------------------------------------------------------------------

_INTERESTING_U32 = (0, 1, 2, 3, 7, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1)


def _choice(rng: np.random.Generator, options: Any) -> Any:
    """One of ``options`` (a sequence), drawn with ``rng``; values keep their Python type."""
    options = list(options)
    return options[int(rng.integers(len(options)))]


def _pick(rng: np.random.Generator, scene: Scene, types: tuple[str, ...]) -> Event | None:
    cands = [e for e in scene.events if e.type in types and e.topic not in scene.channels]
    return cands[int(rng.integers(len(cands)))] if cands else None


def _bad_float(rng: np.random.Generator) -> float:
    return float(_choice(rng, [np.nan, np.inf, -np.inf, 1e308, -1e308, 0.0, 1e-320]))


def _stamp(rng: np.random.Generator, h: dict) -> None:
    kind = int(rng.integers(6))
    if kind == 0:
        h["sec"], h["nanosec"] = 0, 0
    elif kind == 1:
        h["sec"] = int(_choice(rng, [-(2**31), -1, 2**31 - 1]))
    elif kind == 2:
        h["nanosec"] = int(_choice(rng, [10**9, 2**32 - 1]))
    elif kind == 3:
        h["sec"] -= int(rng.integers(1, 100))
    elif kind == 4:
        h["nanosec"] = (h["nanosec"] + int(rng.integers(-400, 400)) * MS) % 10**9
    else:
        h["sec"] += int(rng.integers(1, 3))


def m_image_size(rng, scene):
    """A raw image whose width, height or step do not match its data length."""
    e = _pick(rng, scene, (rm.IMAGE,))
    key = str(_choice(rng, ["width", "height", "step"]))
    choice = int(rng.integers(3))
    if choice == 0:
        e.fields[key] = int(_choice(rng, _INTERESTING_U32))
    else:
        e.fields[key] = max(0, e.fields[key] + int(_choice(rng, [-2, -1, 1, 2])))
    if rng.random() < 0.3:  # keep data consistent with step * height but not with width
        e.fields["data"] = bytes(e.fields["step"] * e.fields["height"] % (1 << 20))


def m_image_data(rng, scene):
    """A raw image with data cut short, padded, emptied or with a multiple-of-a-row length."""
    e = _pick(rng, scene, (rm.IMAGE,))
    data = e.fields["data"]
    kind = int(rng.integers(4))
    if kind == 0:
        e.fields["data"] = data[: int(rng.integers(len(data)))]
    elif kind == 1:
        e.fields["data"] = data + bytes(int(rng.integers(1, 64)))
    elif kind == 2:
        e.fields["data"] = b""
    else:
        e.fields["data"] = data[: len(data) - e.fields["step"]]


def m_image_encoding(rng, scene):
    """A raw image with another encoding, byte order or channel count than its data has."""
    e = _pick(rng, scene, (rm.IMAGE,))
    if rng.random() < 0.3:
        e.fields["is_bigendian"] = int(_choice(rng, [1, 2, 255]))
        return
    e.fields["encoding"] = str(_choice(rng,
        ["", "rgb16", "bayer_rggb8", "32FC1", "16UC1", "mono8", "mono16", "rgba8", "bgra8", "8UC3", "8UC4",
         "yuv422", "64FC1", "RGB8", "rgb8\x00", "\u00e9"]
    ))


def _png_header_bomb(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` but which holds almost no data."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
            + chunk(b"IEND", b""))


def m_compressed(rng, scene):
    """A CompressedImage with corrupt, foreign, truncated or oversized bytes or a bad format."""
    import cv2

    e = _pick(rng, scene, (rm.COMPRESSED_IMAGE,))
    data = bytearray(e.fields["data"])
    kind = int(rng.integers(11))
    if kind == 0:  # flip bytes
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(len(data)))
            data[i] ^= int(rng.integers(1, 256))
        e.fields["data"] = bytes(data)
    elif kind == 1:
        e.fields["data"] = bytes(data[: int(rng.integers(len(data)))])
    elif kind == 2:
        e.fields["data"] = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
    elif kind == 3:
        e.fields["format"] = str(_choice(rng, ["", "tiff", "bmp", "rgb8; compressedDepth png", "jpeg", "png", "jpg"]))
    elif kind == 4:  # a valid image of another size than CameraInfo says
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        e.fields["data"] = encode_compressed(_image(1, h, w), "png")["data"]
    elif kind == 5:  # 16-bit, RGBA or grey png
        img = rng.integers(0, 65535, (CAM_H, CAM_W), dtype=np.uint16) if rng.random() < 0.5 else \
            rng.integers(0, 255, (CAM_H, CAM_W, int(_choice(rng, [1, 4]))), dtype=np.uint8)
        e.fields["data"] = cv2.imencode(".png", img)[1].tobytes()
    elif kind == 6:  # header claims a huge image
        e.fields["data"] = _png_header_bomb(
            int(_choice(rng, [30000, 65535, 2**31 - 1])), int(_choice(rng, [30000, 65535, 1]))
        )
    elif kind == 7:  # jpeg cut before its end marker
        jpg = cv2.imencode(".jpg", _image(2, TAC_H, TAC_W))[1].tobytes()
        e.fields["data"] = jpg[: len(jpg) - int(rng.integers(2, len(jpg) // 2))]
    elif kind == 8:  # other formats OpenCV also reads
        ext = str(_choice(rng, [".bmp", ".tiff", ".ppm", ".webp"]))
        try:
            e.fields["data"] = cv2.imencode(ext, _image(3, CAM_H, CAM_W))[1].tobytes()
        except cv2.error:
            e.fields["data"] = b""
    elif kind == 9:  # zero-size image
        e.fields["data"] = _png_header_bomb(0, 0)
    else:  # a valid png of the wrong size, declared jpeg
        e.fields["format"] = "jpeg"
        e.fields["data"] = encode_compressed(_image(4, 8, 8), "png")["data"]


def m_camera_info(rng, scene):
    """A CameraInfo with bad intrinsics, size, distortion model or coefficients."""
    e = _pick(rng, scene, (rm.CAMERA_INFO,))
    f = e.fields
    kind = int(rng.integers(9))
    if kind == 0:
        f["k"] = [0.0] * 9 if rng.random() < 0.5 else [_bad_float(rng) if rng.random() < 0.5 else v for v in f["k"]]
    elif kind == 1:
        f["k"] = list(f["k"])
        f["k"][int(_choice(rng, [0, 4]))] = float(_choice(rng, [-40.0, 0.0, np.nan, np.inf, 1e-300]))
    elif kind == 2:
        f[str(_choice(rng, ["width", "height"]))] = int(_choice(rng, _INTERESTING_U32))
    elif kind == 3:
        f["distortion_model"] = str(_choice(rng, ["", "equidistant", "fisheye", "rational_polynomial", "plumb_bob"]))
        if not f["d"] or rng.random() < 0.5:
            f["d"] = [0.1, 0.01, 0.0, 0.0, 0.0]
    elif kind == 4:
        f["d"] = [float(v) for v in rng.normal(0.0, 0.5, int(rng.integers(1, 20)))]
    elif kind == 5:
        f["d"] = [_bad_float(rng)] + [0.0] * 4
    elif kind == 6:  # fixed arrays with the wrong count: every later field shifts
        f[str(_choice(rng, ["k", "r", "p"]))] = [1.0] * int(_choice(rng, [0, 8, 10, 13]))
    elif kind == 7:
        f["d"] = [float(v) for v in rng.choice([-1e6, 1e6, 5.0, -5.0], 5)]
    else:
        f["k"] = [float(v) for v in rng.normal(0.0, 100.0, 9)]


def m_tf_values(rng, scene):
    """NaN, inf, zero or huge values in a transform (TF or ground truth)."""
    e = _pick(rng, scene, (rm.TF_MESSAGE, rm.POSE_STAMPED))
    target = (e.fields["transforms"][int(rng.integers(len(e.fields["transforms"])))] if e.type == rm.TF_MESSAGE
              else e.fields)
    kind = int(rng.integers(4))
    if kind == 0:
        target["t"] = list(target["t"])
        target["t"][int(rng.integers(3))] = _bad_float(rng)
    elif kind == 1:
        target["q"] = list(target["q"])
        target["q"][int(rng.integers(4))] = _bad_float(rng)
    elif kind == 2:
        target["q"] = [0.0, 0.0, 0.0, 0.0]
    else:
        target["q"] = [float(v) for v in rng.normal(0.0, 1e-12, 4)]


def m_tf_tree(rng, scene):
    """A TF tree with a self-loop, a second parent, a loop, an empty name or a missing edge."""
    e = _pick(rng, scene, (rm.TF_MESSAGE,))
    tr = e.fields["transforms"][int(rng.integers(len(e.fields["transforms"])))]
    kind = int(rng.integers(6))
    if kind == 0:
        tr["child"] = tr["header"]["frame_id"]
    elif kind == 1:
        tr["header"]["frame_id"] = str(_choice(rng, ["front_optical", "ee", "tactile_left_optical", "other"]))
    elif kind == 2:
        tr["child"] = str(_choice(rng, ["world", "ee", "front_optical", ""]))
    elif kind == 3:
        tr["header"]["frame_id"] = ""
    elif kind == 4:
        tr["child"], tr["header"]["frame_id"] = tr["header"]["frame_id"], tr["child"]
    else:
        e.fields["transforms"] = [t for t in e.fields["transforms"] if t is not tr]


def m_stamps(rng, scene):
    """Out-of-order, duplicated, zero, negative or out-of-range stamps and log times."""
    kind = int(rng.integers(5))
    if kind == 0:  # swap the header stamps of two messages of one topic
        topic = str(_choice(rng, sorted({ev.topic for ev in scene.events if "header" in ev.fields})))
        evs = [ev for ev in scene.events if ev.topic == topic]
        if len(evs) >= 2:
            a, b = rng.choice(len(evs), 2, replace=False)
            ha, hb = evs[a].fields["header"], evs[b].fields["header"]
            ha["sec"], hb["sec"], ha["nanosec"], hb["nanosec"] = hb["sec"], ha["sec"], hb["nanosec"], ha["nanosec"]
    elif kind == 1:  # one stamp moved anywhere
        e = _pick(rng, scene, (rm.IMAGE, rm.COMPRESSED_IMAGE, rm.CAMERA_INFO, rm.TF_MESSAGE, rm.POSE_STAMPED,
                               rm.JOINT_STATE, rm.WRENCH_STAMPED))
        h = (e.fields["transforms"][0]["header"] if e.type == rm.TF_MESSAGE and e.fields["transforms"]
             else e.fields.get("header"))
        if h is not None:
            _stamp(rng, h)
    elif kind == 2:  # log times out of order
        e = scene.events[int(rng.integers(len(scene.events)))]
        e.log_time = int(max(0, e.log_time + int(rng.integers(-500, 500)) * MS))
    elif kind == 3:  # extreme log time
        e = scene.events[int(rng.integers(len(scene.events)))]
        e.log_time = int(_choice(rng, [0, 1, 2**63 - 1, 2**64 - 1]))
    else:  # every image stamp of one topic reversed
        topic = str(_choice(rng, ["/cameras/front/image", "/cameras/side/image/compressed", "/tactile/left/depth"]))
        evs = [ev for ev in scene.events if ev.topic == topic]
        stamps = [(ev.fields["header"]["sec"], ev.fields["header"]["nanosec"]) for ev in evs][::-1]
        for ev, (s, n) in zip(evs, stamps):
            ev.fields["header"]["sec"], ev.fields["header"]["nanosec"] = s, n


def m_values(rng, scene):
    """NaN or inconsistent values in the contact, wrench and joint-state topics."""
    e = _pick(rng, scene, (rm.BOOL, rm.WRENCH_STAMPED, rm.JOINT_STATE))
    if e.type == rm.BOOL:
        e.fields["data"] = int(_choice(rng, [2, 127, 255]))
    elif e.type == rm.WRENCH_STAMPED:
        e.fields["force"] = [_bad_float(rng), 0.0, _bad_float(rng)]
    else:
        kind = int(rng.integers(3))
        if kind == 0:
            e.fields["position"] = [_bad_float(rng)] * len(e.fields["position"])
        elif kind == 1:
            e.fields["position"] = e.fields["position"][:1]
        else:
            e.fields["name"] = ["finger_joint1", "\xff"] + [str(i) for i in range(int(rng.integers(5)))]


def m_cdr(rng, scene):
    """Raw CDR bytes cut short, padded, flipped, re-headed or with a huge length prefix."""
    e = scene.events[int(rng.integers(len(scene.events)))]
    data = bytearray(encode(e.type, e.fields))
    kind = int(rng.integers(6))
    if kind == 0:
        data = data[: int(rng.integers(len(data)))]
    elif kind == 1:
        data += rng.integers(0, 256, int(rng.integers(1, 32)), dtype=np.uint8).tobytes()
    elif kind == 2:
        for _ in range(int(rng.integers(1, 6))):
            i = int(rng.integers(len(data)))
            data[i] ^= 1 << int(rng.integers(8))
    elif kind == 3:
        # encapsulation: big-endian CDR, XCDR2, garbage, PL_CDR_LE
        data[0:4] = [b"\x00\x00\x00\x00", b"\x00\x07\x00\x00", b"\xff\xff\xff\xff", b"\x00\x03\x00\x00"][
            int(rng.integers(4))
        ]
    elif kind == 4 and len(data) >= 8:  # a length-like u32 (4-aligned) set to a huge value
        i = 4 + 4 * int(rng.integers((len(data) - 4) // 4))
        data[i : i + 4] = struct.pack("<I", int(_choice(rng, [2**31, 2**32 - 1, 0x7FFFFFF0, 1 << 24])))
    else:
        data = bytearray(data[:4])
    e.raw = bytes(data)


def m_schema(rng, scene):
    """A corrupt schema text, another schema name, or unsupported encodings for one topic."""
    topics = sorted({e.topic for e in scene.events})
    topic = str(_choice(rng, topics))
    type_name = next(e.type for e in scene.events if e.topic == topic)
    text = rm.definition(type_name)
    kind = int(rng.integers(7))
    o: dict[str, str] = {}
    if kind == 0:
        lines = text.splitlines()
        del lines[int(rng.integers(len(lines)))]
        o["schema_text"] = "\n".join(lines)
    elif kind == 1:
        b = bytearray(text.encode())
        for _ in range(int(rng.integers(1, 6))):
            b[int(rng.integers(len(b)))] = int(rng.integers(32, 127))
        o["schema_text"] = b.decode()
    elif kind == 2:
        o["schema_name"] = str(_choice(rng, list(rm.MESSAGE_TYPES) + ["", "pkg/Unknown", "a/b/c/d"]))
    elif kind == 3:
        o["schema_encoding"] = str(_choice(rng, ["ros1msg", "jsonschema", "", "protobuf"]))
    elif kind == 4:
        o["message_encoding"] = str(_choice(rng, ["json", "ros1", "", "cdr2"]))
    elif kind == 5:
        o["schema_text"] = ""
    else:
        o["topic"] = str(_choice(rng, ["/tf", "/contact", "", topic + "_x"]))
    scene.channels[topic] = o


def m_messages(rng, scene):
    """Messages dropped or duplicated (a missing CameraInfo, a repeated image, an empty topic)."""
    kind = int(rng.integers(3))
    if kind == 0:
        del scene.events[int(rng.integers(len(scene.events)))]
    elif kind == 1:
        e = scene.events[int(rng.integers(len(scene.events)))]
        scene.events.append(
            Event(e.log_time, e.topic, e.type, json.loads(json.dumps(e.fields, default=_jsonable)), e.raw)
        )
    else:
        topic = str(_choice(rng, sorted({e.topic for e in scene.events})))
        scene.events = [e for e in scene.events if e.topic != topic]


def _jsonable(v: Any) -> Any:
    if isinstance(v, bytes):
        return list(v)
    raise TypeError(type(v))


MESSAGE_MUTATIONS = {
    "image_size": m_image_size, "image_data": m_image_data, "image_encoding": m_image_encoding,
    "compressed": m_compressed, "camera_info": m_camera_info, "tf_values": m_tf_values, "tf_tree": m_tf_tree,
    "stamps": m_stamps, "values": m_values, "cdr": m_cdr, "schema": m_schema, "messages": m_messages,
}

# --- byte-level mutations ---------------------------------------------------------------------


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records after the magic, while they parse."""
    out, pos = [], 8
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, length))
        if op == 0x02 or pos + 9 + length > len(data) - 8:  # footer or a broken length
            break
        pos += 9 + length
    return out


def b_bitflip(rng, data: bytearray) -> bytearray:
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(len(data)))
        data[i] ^= 1 << int(rng.integers(8))
    return data


def b_bytes(rng, data: bytearray) -> bytearray:
    for _ in range(int(rng.integers(1, 4))):
        i = int(rng.integers(len(data)))
        v = [b"\x00", b"\xff", b"\x7f", b"\x80", b"\x00\x00\x00\x00", b"\xff\xff\xff\xff",
             b"\xff\xff\xff\xff\xff\xff\xff\x7f"][int(rng.integers(7))]
        data[i : i + len(v)] = v
    return data


def b_truncate(rng, data: bytearray) -> bytearray:
    return data[: int(rng.integers(len(data)))]


def b_splice(rng, data: bytearray) -> bytearray:
    i = int(rng.integers(len(data)))
    n = int(rng.integers(1, 64))
    if rng.random() < 0.5:
        return data[:i] + data[i + n :]
    return data[:i] + bytearray(rng.integers(0, 256, n, dtype=np.uint8).tobytes()) + data[i:]


def b_record_length(rng, data: bytearray) -> bytearray:
    """A top-level record's length field set to a wrong value."""
    recs = _records(bytes(data))
    if not recs:
        return b_bitflip(rng, data)
    pos, _op, length = recs[int(rng.integers(len(recs)))]
    new = int(_choice(rng, [0, 1, 8, length - 1, length + 1, length * 2, len(data), 2**31, 2**63 - 1, 2**64 - 1]))
    data[pos + 1 : pos + 9] = struct.pack("<Q", max(0, min(new, 2**64 - 1)))
    return data


def b_chunk_payload(rng, data: bytearray) -> bytearray:
    """Bytes inside an uncompressed chunk changed, its CRC recomputed (or zeroed)."""
    chunks = [(p, n) for p, op, n in _records(bytes(data)) if op == 0x06]
    if not chunks:
        return b_bitflip(rng, data)
    pos, length = chunks[int(rng.integers(len(chunks)))]
    body = pos + 9
    usize, crc, clen = struct.unpack_from("<QII", data, body + 16)
    comp = bytes(data[body + 32 : body + 32 + clen])
    (dlen,) = struct.unpack_from("<Q", data, body + 32 + clen)
    start = body + 40 + clen
    if comp != b"" or dlen == 0:
        return b_bitflip(rng, data)
    payload = bytearray(data[start : start + dlen])
    kind = int(rng.integers(3))
    if kind == 0:  # flip bits
        for _ in range(int(rng.integers(1, 6))):
            i = int(rng.integers(len(payload)))
            payload[i] ^= 1 << int(rng.integers(8))
    elif kind == 1:  # an inner record's length
        inner, p = [], 0
        while p + 9 <= len(payload):
            op, n = struct.unpack_from("<BQ", payload, p)
            inner.append(p)
            p += 9 + n
        p = inner[int(rng.integers(len(inner)))] if inner else 0
        payload[p + 1 : p + 9] = struct.pack("<Q", int(_choice(rng, [0, 1, 3, 20, 2**32, 2**63])))
    else:  # a message's data bytes: the CDR the decoder sees
        i = int(rng.integers(len(payload)))
        payload[i : i + 4] = rng.integers(0, 256, 4, dtype=np.uint8).tobytes()
        payload = payload[: len(data[start : start + dlen])]
    new_crc = 0 if rng.random() < 0.3 else zlib.crc32(payload)
    data[start : start + dlen] = payload
    struct.pack_into("<I", data, body + 24, new_crc)
    return data


def b_summary(rng, data: bytearray) -> bytearray:
    """A wrong offset or time in the summary (chunk index, footer) or a wrong magic."""
    recs = _records(bytes(data))
    kind = int(rng.integers(3))
    if kind == 0:
        idx = [(p, n) for p, op, n in recs if op == 0x08]  # chunk index
        if idx:
            p, _n = idx[int(rng.integers(len(idx)))]
            field_at = p + 9 + int(_choice(rng, [0, 8, 16, 24]))  # start/end time, chunk offset, chunk length
            struct.pack_into("<Q", data, field_at, int(_choice(rng, [0, 1, 2**62, len(data), len(data) - 40])))
            return data
    if kind == 1 and len(data) > 37:
        off = len(data) - 8 - 20 + int(_choice(rng, [0, 8]))  # footer summary_start / summary_offset_start
        struct.pack_into("<Q", data, off, int(_choice(rng, [0, 1, 8, len(data) - 30, len(data), 2**63])))
        return data
    i = int(_choice(rng, [0, len(data) - 8]))
    data[i + int(rng.integers(8))] ^= 0xFF
    return data


BYTE_MUTATIONS = {
    "bitflip": b_bitflip, "bytes": b_bytes, "truncate": b_truncate, "splice": b_splice,
    "record_length": b_record_length, "chunk_payload": b_chunk_payload, "summary": b_summary,
}

# --- inputs -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spec:
    """One fuzz input: a layout, message-level then byte-level mutations, each with its own seed."""

    layout: str
    message: tuple[tuple[str, int], ...] = ()
    byte: tuple[tuple[str, int], ...] = ()

    def describe(self) -> str:
        parts = [f"layout={self.layout}"]
        parts += [f"msg:{n}@{s}" for n, s in self.message] + [f"byte:{n}@{s}" for n, s in self.byte]
        return " ".join(parts)

    @staticmethod
    def parse(text: str) -> Spec:
        """The Spec that ``describe`` printed as ``text``."""
        parts = text.split()
        message, byte = [], []
        for part in parts[1:]:
            kind, _, rest = part.partition(":")
            name, _, seed = rest.partition("@")
            (message if kind == "msg" else byte).append((name, int(seed)))
        return Spec(parts[0].split("=", 1)[1], tuple(message), tuple(byte))

    def smaller(self) -> list[Spec]:
        """Candidate simplifications: the most compact layout, or one mutation fewer."""
        out = [] if self.layout == "zstd" else [replace(self, layout="zstd")]
        out += [replace(self, message=self.message[:i] + self.message[i + 1 :]) for i in range(len(self.message))]
        out += [replace(self, byte=self.byte[:i] + self.byte[i + 1 :]) for i in range(len(self.byte))]
        return [c for c in out if c.message or c.byte]


def build_input(spec: Spec) -> bytes:
    """The MCAP bytes of ``spec``: the base scene, mutated, written, then mutated as bytes."""
    scene = base_scene()
    for name, seed in spec.message:
        try:
            MESSAGE_MUTATIONS[name](np.random.default_rng(seed), scene)
        except (ValueError, IndexError, TypeError, AttributeError):
            pass  # the mutation does not apply to this scene (e.g. nothing left to pick)
    scene.events.sort(key=lambda e: e.log_time)
    data = bytearray(write_scene(scene, spec.layout))
    for name, seed in spec.byte:
        if data:
            try:
                data = BYTE_MUTATIONS[name](np.random.default_rng(seed), bytearray(data))
            except (struct.error, ValueError, IndexError):
                pass  # the structure it targets is already broken by an earlier mutation
    return bytes(data)


def random_spec(rng: np.random.Generator) -> Spec:
    """A random input: at least one mutation, message-level, byte-level or both."""
    layout = str(_choice(rng, LAYOUTS))
    while True:
        nm = int(_choice(rng, [0, 1, 1, 1, 2, 3]))
        nb = int(_choice(rng, [0, 0, 1, 1, 2]))
        if nm + nb:
            break
    msg = tuple((str(_choice(rng, list(MESSAGE_MUTATIONS))), int(rng.integers(2**31))) for _ in range(nm))
    byte = tuple((str(_choice(rng, list(BYTE_MUTATIONS))), int(rng.integers(2**31))) for _ in range(nb))
    return Spec(layout, msg, byte)


# --- running the commands in a worker process ---------------------------------------------------


def _worker_main() -> None:
    """Read jobs (JSON lines: ``{"argv": [...]}``) on stdin, run ``mvtop`` in this process,
    answer with one JSON line per job on the original stdout."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    from mvtop_cli.cli import main

    for line in sys.stdin:
        job = json.loads(line)
        proto.write(json.dumps(_run_in_process(main, job["argv"])) + "\n")


def _run_in_process(main, argv: list[str]) -> dict:
    """Exit code, captured stdout/stderr (Python and C level) and any traceback of one run."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        code: int | None = 0
        tb = None
        t = time.perf_counter()
        c = time.process_time()
        try:
            main(argv)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except Exception:  # the failures the fuzzer looks for: report them, keep serving
            code, tb = None, traceback.format_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        out.seek(0)
        err.seek(0)
        return {"code": code, "stdout": out.read().decode("utf-8", "replace")[-4000:],
                "stderr": err.read().decode("utf-8", "replace")[-4000:], "traceback": tb,
                "seconds": time.perf_counter() - t, "cpu_seconds": time.process_time() - c}


WALL_FACTOR = 5  # a job is a hang after this many times its CPU-time limit in wall time


class Worker:
    """A ``mvtop`` worker process; ``run`` kills and restarts it when a job exceeds ``timeout`` s of
    CPU time (see ``_answered``)."""

    def __init__(self, timeout: float, memory_gb: float = 6.0, env: dict[str, str] | None = None):
        self.timeout = timeout
        self.memory_gb = memory_gb
        self.env = env or {}
        self.proc: subprocess.Popen | None = None
        self.last_cpu = 0.0  # CPU seconds [s] of the commands of the last run_input (see run_input)

    def _start(self) -> None:
        env = dict(os.environ, MVTOP_FUZZ_MEMORY_GB=str(self.memory_gb), **self.env)
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--worker"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, cwd=str(REPO),
        )

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None

    def _kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None

    def _cpu_seconds(self) -> float | None:
        """CPU time [s] the worker process has used (its threads too), or None off Linux."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime

    def _answered(self, limit: float) -> bool:
        """Whether the worker answers before it has used ``limit`` s of CPU time for this job, or
        ``WALL_FACTOR * limit`` s of wall time (a deadlock uses no CPU). CPU time, not wall time,
        so that a machine busy with other work does not turn a slow input into a ``hang``."""
        cpu0, t0 = self._cpu_seconds(), time.monotonic()
        while True:
            wall = time.monotonic() - t0
            cpu = self._cpu_seconds()
            used = wall if cpu is None or cpu0 is None else cpu - cpu0
            if used >= limit or wall >= WALL_FACTOR * limit:
                return False
            step = min(limit - used, WALL_FACTOR * limit - wall, 0.5)
            if select.select([self.proc.stdout], [], [], max(step, 0.0))[0]:
                return True

    def run(self, argv: list[str], timeout: float | None = None) -> dict:
        if self.proc is None:
            self._start()
        assert self.proc is not None
        self.proc.stdin.write((json.dumps({"argv": argv}) + "\n").encode())
        self.proc.stdin.flush()
        if not self._answered(self.timeout if timeout is None else timeout):
            self._kill()
            return {"code": None, "hang": True, "stdout": "", "stderr": "", "traceback": None}
        line = self.proc.stdout.readline()
        if not line:
            rc = self.proc.wait()
            self.proc = None
            return {"code": None, "died": rc, "stdout": "", "stderr": "", "traceback": None}
        return json.loads(line)

    def __enter__(self) -> Worker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _files_in(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []


def classify(command: str, result: dict, log: Path, out_dir: Path | None) -> tuple[str, str]:
    """(outcome, detail) of one command's run (see the module docstring)."""
    if result.get("hang"):
        return "hang", "time limit exceeded"
    if "died" in result:
        return "died", f"worker exited with {result['died']}"
    if result["traceback"] is not None:
        return "crash", result["traceback"]
    stderr = result["stderr"].strip().splitlines()
    files = _files_in(out_dir) if out_dir is not None else []
    if result["code"] == 0:
        other = [ln for ln in stderr if not ln.startswith("mvtop: warning:") and not PROGRESS_LINE.match(ln)]
        if other:
            return "noisy", "\n".join(stderr)
        if out_dir is None:
            return "ok", ""
        if files != sorted(OUTPUT_FILES):
            return "partial", f"output folder holds {files}"
        summary = json.loads((out_dir / "summary.json").read_text())
        return ("skipped", f"{summary['frames_skipped']} frames skipped") if summary["frames_skipped"] else ("ok", "")
    if result["code"] == 2 and len(stderr) == 1 and stderr[0].startswith("mvtop: error: ") and log.name in stderr[0]:
        if files:
            return "partial", f"failed run left {files}"
        return "error", stderr[0]
    return "unclear", f"exit {result['code']}: " + "\n".join(stderr)


def run_input(worker: Worker, data: bytes, config: Path, folder: Path, name: str = "log") -> dict[str, tuple[str, str]]:
    """Write ``data`` as ``folder/name.mcap`` and run inspect and estimate on it:
    ``{command: (outcome, detail)}``."""
    log = folder / f"{name}.mcap"
    out_dir = folder / f"{name}_out"
    log.write_bytes(data)
    shutil.rmtree(out_dir, ignore_errors=True)
    res = {}
    r = worker.run(["inspect", str(log), "--config", str(config)])
    res["inspect"] = classify("inspect", r, log, None)
    worker.last_cpu = r.get("cpu_seconds", 0.0)
    r = worker.run(["estimate", str(log), "--config", str(config), "--out", str(out_dir),
                    "--particles", "10", "--seed", "0"])
    res["estimate"] = classify("estimate", r, log, out_dir)
    worker.last_cpu += r.get("cpu_seconds", 0.0)
    shutil.rmtree(out_dir, ignore_errors=True)
    return res


def error_kind(line: str) -> str:
    """An error line without the log path, numbers and quoted names: what kind of error it is."""
    text = re.sub(r"^mvtop: error: \S+?: ", "", line)
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'…'", text)
    text = re.sub(r"\[[^\]]*\]", "[…]", text)
    text = re.sub(r"-?\d[\w.+-]*", "N", text)
    return text[:90]


def shrink(worker: Worker, spec: Spec, config: Path, folder: Path, command: str, sig: str) -> tuple[Spec, bytes]:
    """Greedily simplify a failing ``spec`` (``Spec.smaller``) while ``command`` still fails
    with the same signature; returns the simplest spec found and its input."""
    best, data = spec, build_input(spec)
    improved = True
    while improved:
        improved = False
        for cand in best.smaller():
            cand_data = build_input(cand)
            outcome, detail = run_input(worker, cand_data, config, folder, "input")[command]
            if outcome in FAILURES and signature(outcome, detail) == sig:
                best, data, improved = cand, cand_data, True
                break
    return best, data


def signature(outcome: str, detail: str) -> str:
    """A failure's identity for de-duplication: the outcome and the last traceback frame and
    exception type (or the first line of the message)."""
    lines = [ln.strip() for ln in detail.strip().splitlines() if ln.strip()]
    if outcome == "crash" and lines:
        where = next((ln for ln in reversed(lines) if ln.startswith("File ")), "")
        return f"crash {lines[-1].split(':')[0]} {where}"
    return f"{outcome} {lines[0][:80] if lines else ''}"


# --- the command line -----------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--count", type=int, default=1000, help="number of mutated inputs (default 1000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the input generator (default 0)")
    ap.add_argument("--timeout", type=float, default=30.0,
                    help="CPU-time limit per command and input [s] (default 30; 5x in wall time)")
    ap.add_argument("--keep", type=Path, default=Path("fuzz_failures"),
                    help="folder for failing inputs (default ./fuzz_failures)")
    ap.add_argument("--no-shrink", dest="shrink", action="store_false",
                    help="keep failing inputs as found (default: simplify each while it still fails)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes running inputs in parallel (default 1)")
    ap.add_argument("--kinds", type=int, default=12, help="list this many most frequent kinds of error (default 12)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        _limit_memory()
        _worker_main()
        return 0
    t_start = time.perf_counter()
    counts: dict[str, Counter] = {c: Counter() for c in COMMANDS}
    errors: dict[str, Counter] = {c: Counter() for c in COMMANDS}
    failures: dict[str, tuple[int, Spec, bytes, str, str]] = {}
    failure_counts: Counter = Counter()
    master = np.random.default_rng(args.seed)
    specs = [random_spec(master) for _ in range(args.count)]  # the same inputs whatever --jobs is
    kinds = Counter(
        [f"msg:{n}" for sp in specs for n, _ in sp.message] + [f"byte:{n}" for sp in specs for n, _ in sp.byte]
    )
    cpu = [0.0]
    lock = threading.Lock()
    pending = iter(range(args.count))
    crashed: list[BaseException] = []

    def record(i: int, data: bytes, res: dict[str, tuple[str, str]]) -> None:
        for command, (outcome, detail) in res.items():
            counts[command][outcome] += 1
            if outcome == "error":
                errors[command][error_kind(detail)] += 1
            if outcome in FAILURES:
                sig = f"{command}: {signature(outcome, detail)}"
                if sig not in failures:  # write it at once: a long run may be stopped
                    print(f"  new failure at input {i}: {sig} [{specs[i].describe()}]", flush=True)
                    args.keep.mkdir(parents=True, exist_ok=True)
                    stem = args.keep / f"found_{len(failures):03d}"
                    stem.with_suffix(".mcap").write_bytes(data)
                    stem.with_suffix(".txt").write_text(f"{sig}\ninput {i}: {specs[i].describe()}\n\n{detail}\n")
                if sig not in failures or (len(data), i) < (len(failures[sig][2]), failures[sig][0]):
                    failures[sig] = (i, specs[i], data, outcome, detail)
                failure_counts[sig] += 1

    def serve(worker: Worker, folder: Path, config: Path) -> None:
        try:
            while True:
                with lock:
                    i = next(pending, None)
                if i is None:
                    return
                data = build_input(specs[i])
                res = run_input(worker, data, config, folder, "input")
                with lock:
                    record(i, data, res)
                    cpu[0] += worker.last_cpu
                    done = sum(counts[COMMANDS[0]].values())
                    if done % 500 == 0:
                        el = time.perf_counter() - t_start
                        print(f"  {done}/{args.count} inputs, {el:.0f} s, failures so far: {len(failures)}", flush=True)
        except BaseException as err:  # reported by the main thread
            crashed.append(err)

    with tempfile.TemporaryDirectory(prefix="mvtop-fuzz-") as tmp:
        folder = Path(tmp)
        config = write_config(folder / "config")
        workers = [Worker(args.timeout) for _ in range(max(args.jobs, 1))]
        try:
            base = run_input(workers[0], write_scene(base_scene()), config, folder, "base")
            if any(o[0] != "ok" for o in base.values()):
                print(f"the unmutated base log does not run cleanly: {base}", file=sys.stderr)
                return 1
            threads = []
            for k, worker in enumerate(workers):
                (folder / f"w{k}").mkdir()
                threads.append(threading.Thread(target=serve, args=(worker, folder / f"w{k}", config)))
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            if crashed:
                raise crashed[0]
            if args.shrink:
                for sig, (i, spec, _data, outcome, detail) in list(failures.items()):
                    command = sig.split(":", 1)[0]
                    small, small_data = shrink(workers[0], spec, config, folder, command, sig.split(": ", 1)[1])
                    failures[sig] = (i, small, small_data, outcome, detail)
        finally:
            for worker in workers:
                worker.close()
    elapsed = time.perf_counter() - t_start
    print(f"mvtop log fuzzing: {args.count} inputs (seed {args.seed}), {elapsed:.1f} s with {args.jobs} worker(s) "
          f"({elapsed / max(args.count, 1):.3f} s per input; commands' CPU time {cpu[0] / max(args.count, 1):.3f} s "
          "per input, both commands)")
    print(f"{'outcome':<10}" + "".join(f"{c:>10}" for c in COMMANDS))
    for outcome in GOOD + FAILURES:
        if any(counts[c][outcome] for c in COMMANDS) or outcome in GOOD:
            print(f"{outcome:<10}" + "".join(f"{counts[c][outcome]:>10}" for c in COMMANDS))
    print("mutations applied: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    for command in COMMANDS:
        if args.kinds and errors[command]:
            print(f"most frequent errors of {command} ({len(errors[command])} kinds):")
            for kind, n in errors[command].most_common(args.kinds):
                print(f"  {n:6d}  {kind}")
    if failures:
        args.keep.mkdir(parents=True, exist_ok=True)
        print(f"{len(failures)} distinct failures (smallest input of each in {args.keep}):")
        for k, (sig, (i, spec, data, _outcome, detail)) in enumerate(sorted(failures.items())):
            stem = f"failure_{k:03d}"
            (args.keep / f"{stem}.mcap").write_bytes(data)
            (args.keep / f"{stem}.txt").write_text(f"{sig}\ninput {i}: {spec.describe()}\n\n{detail}\n")
            print(f"  {stem}: {sig}  [{failure_counts[sig]} inputs; smallest: input {i}: {spec.describe()}]")
        return 1
    return 0


def _limit_memory() -> None:
    """Cap the worker's address space so a runaway allocation fails (MemoryError) instead of
    exhausting a shared machine."""
    import resource

    gb = float(os.environ.get("MVTOP_FUZZ_MEMORY_GB", "0") or 0)
    if gb > 0:
        limit = int(gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


if __name__ == "__main__":
    sys.exit(main())
