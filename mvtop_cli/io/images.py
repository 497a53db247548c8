"""Decode sensor_msgs Image / CompressedImage messages to numpy arrays, and encode them back.

Colour images come out as (H, W, 3) uint8 RGB (mono is expanded to three channels,
16-bit mono is scaled to 8 bits); depth images as (H, W) float32 [m]. OpenCV is imported
when first needed (only for compressed images).
"""

from __future__ import annotations

import os
import re
import struct
import sys
import tempfile
from typing import Any

import numpy as np

from ..errors import LogError

# encoding -> (channels, numpy dtype of one channel)
COLOR_ENCODINGS: dict[str, tuple[int, str]] = {
    "rgb8": (3, "u1"),
    "bgr8": (3, "u1"),
    "rgba8": (4, "u1"),
    "bgra8": (4, "u1"),
    "mono8": (1, "u1"),
    "8UC1": (1, "u1"),
    "mono16": (1, "u2"),
    "8UC3": (3, "u1"),  # OpenCV's untyped 3-channel 8-bit: treated as bgr8, as cv_bridge does
}
DEPTH_ENCODINGS: dict[str, tuple[int, str]] = {
    "32FC1": (1, "f4"),  # metres (REP 118)
    "16UC1": (1, "u2"),  # millimetres (REP 118)
}
COMPRESSED_FORMATS: tuple[str, ...] = ("png", "jpeg")
# Recorded object masks (label images): one channel of 8 or 16 bits; lossless png when compressed.
MASK_ENCODINGS: dict[str, tuple[int, str]] = {
    "mono8": (1, "u1"),
    "8UC1": (1, "u1"),
    "mono16": (1, "u2"),
    "16UC1": (1, "u2"),
}


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise LogError(
            "decoding compressed images needs OpenCV: pip install opencv-python-headless"
        ) from err
    return cv2


def _raw_array(msg: Any, topic: str, table: dict[str, tuple[int, str]], kind: str) -> tuple[np.ndarray, str]:
    """The pixel array (H, W, C) of a raw Image message, checked against its step and size."""
    encoding = str(msg.encoding)
    if encoding not in table:
        supported = ", ".join(table)
        raise LogError(
            f"topic {topic!r}: unsupported {kind} image encoding {encoding!r} (supported: {supported})"
        )
    channels, dtype = table[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = msg.data
    if height <= 0 or width <= 0:
        raise LogError(f"topic {topic!r}: {encoding} image of {width}x{height} px (expected a non-empty image)")
    itemsize = np.dtype(dtype).itemsize
    row_bytes = width * channels * itemsize
    if step < row_bytes or len(data) != step * height:
        raise LogError(
            f"topic {topic!r}: {encoding} image of {width}x{height} has step {step} and "
            f"{len(data)} data bytes (expected step >= {row_bytes} and step*height = {step * height} bytes)"
        )
    order = ">" if int(msg.is_bigendian) and itemsize > 1 else "<"
    buf = np.frombuffer(data, dtype=np.uint8).reshape(height, step)[:, :row_bytes]
    arr = np.ascontiguousarray(buf).view(order + dtype).reshape(height, width, channels)
    return arr, encoding


def _to_rgb(arr: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "mono16":
        arr = (arr.astype(np.uint16) >> 8).astype(np.uint8)
    if arr.shape[2] == 1:
        return np.repeat(arr, 3, axis=2)
    if encoding in ("bgr8", "bgra8", "8UC3"):
        return np.ascontiguousarray(arr[:, :, 2::-1])
    return np.ascontiguousarray(arr[:, :, :3])


def _check_size(width: int, height: int, expected: tuple[int, int] | None, topic: str, what: str) -> None:
    if expected is not None and (width, height) != tuple(expected):
        raise LogError(
            f"topic {topic!r}: {what} of {width}x{height} px but CameraInfo says {expected[0]}x{expected[1]} "
            "(expected images of the calibrated size)"
        )


def decode_image(msg: Any, topic: str = "", expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A sensor_msgs Image or CompressedImage -> (H, W, 3) uint8 RGB.

    Raw encodings: rgb8, bgr8, rgba8, bgra8, mono8, mono16 (scaled to 8 bits), 8UC1, 8UC3.
    Compressed formats: png and jpeg (any ``format`` string naming them, as
    image_transport writes e.g. ``"rgb8; jpeg compressed bgr8"``). ``expected_size``
    (width, height) [px], e.g. from CameraInfo, rejects an image of another size (a
    compressed one before it is decoded, when its header tells the size).
    """
    if hasattr(msg, "format"):
        return decode_compressed(msg, topic, expected_size)
    arr, encoding = _raw_array(msg, topic, COLOR_ENCODINGS, "colour")
    _check_size(arr.shape[1], arr.shape[0], expected_size, topic, f"{encoding} image")
    return _to_rgb(arr, encoding)


def decode_depth(msg: Any, topic: str = "", expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A sensor_msgs Image with encoding 32FC1 [m] or 16UC1 [mm] -> (H, W) float32 [m]
    (``expected_size`` as in ``decode_image``)."""
    if hasattr(msg, "format"):
        raise LogError(
            f"topic {topic!r}: compressed depth ({msg.format!r}) is not supported "
            "(expected a raw sensor_msgs/msg/Image with encoding 32FC1 or 16UC1)"
        )
    arr, encoding = _raw_array(msg, topic, DEPTH_ENCODINGS, "depth")
    _check_size(arr.shape[1], arr.shape[0], expected_size, topic, f"{encoding} depth image")
    if encoding == "16UC1":
        return (arr[:, :, 0].astype(np.float32) * np.float32(1e-3)).astype(np.float32)
    return arr[:, :, 0].astype(np.float32)


def decode_mask(msg: Any, topic: str = "", expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A recorded object mask -> (H, W) uint16 labels as published (0 = background).

    A raw sensor_msgs Image with encoding mono8, 8UC1, mono16 or 16UC1, or a CompressedImage
    in png (8 or 16 bits, one channel); jpeg is refused (lossy compression changes label
    values along the edges). ``expected_size`` as in ``decode_image``.
    """
    expected = "expected a mask as sensor_msgs/Image mono8 or mono16, or a one-channel png CompressedImage"
    if hasattr(msg, "format"):
        fmt = str(msg.format)
        if compressed_codec(fmt) != "png":
            raise LogError(f"topic {topic!r}: mask in compressed format {fmt!r} ({expected})")
        data = bytes(msg.data)
        header = stream_size(data)
        if header is not None:
            _check_size(header[1], header[2], expected_size, topic, "png mask")
        img, diagnostics = _imdecode(_cv2(), data)
        if img is None:
            why = f": {diagnostics[0]}" if diagnostics else ""
            raise LogError(f"topic {topic!r}: {len(data)} bytes do not decode as png{why} ({expected})")
        if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
            channels = img.shape[2] if img.ndim == 3 else 1
            raise LogError(f"topic {topic!r}: png mask has {channels} channels of {img.dtype} ({expected})")
        _check_size(img.shape[1], img.shape[0], expected_size, topic, "decoded mask")
        return img.astype(np.uint16)
    encoding = str(msg.encoding)
    if encoding not in MASK_ENCODINGS:
        raise LogError(f"topic {topic!r}: mask encoding {encoding!r} is not supported ({expected})")
    arr, encoding = _raw_array(msg, topic, MASK_ENCODINGS, "mask")
    _check_size(arr.shape[1], arr.shape[0], expected_size, topic, f"{encoding} mask")
    return arr[:, :, 0].astype(np.uint16)


def compressed_codec(fmt: str) -> str | None:
    """``png`` or ``jpeg`` for a CompressedImage ``format`` string, None if neither."""
    f = fmt.lower()
    if "compresseddepth" in f.replace(" ", ""):
        return None
    if "png" in f:
        return "png"
    if "jpeg" in f or "jpg" in f:
        return "jpeg"
    return None


_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (they hold the image size): C0-CF except DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def stream_size(data: bytes) -> tuple[str, int, int] | None:
    """``(codec, width, height)`` [px] from the header of a png or jpeg stream, without
    decoding it; None when the header cannot be read (the decoder then reports why)."""
    data = bytes(data[:65536]) if len(data) > 65536 else bytes(data)
    if data[:8] == _PNG_MAGIC and len(data) >= 24 and data[12:16] == b"IHDR":
        width, height = struct.unpack_from(">II", data, 16)
        return "png", width, height
    if data[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack_from(">H", data, pos + 2)
        if marker in _JPEG_SOF:
            if pos + 9 > len(data):
                return None
            height, width = struct.unpack_from(">HH", data, pos + 5)
            return "jpeg", width, height
        if marker in (0xD9, 0xDA) or length < 2:  # end of image or start of scan: no frame header before
            return None
        pos += 2 + length
    return None


def _imdecode(cv2: Any, data: bytes) -> tuple[Any, list[str]]:
    """``cv2.imdecode`` with the codecs' diagnostics captured: libpng and libjpeg write them
    straight to file descriptor 2, and a command line must keep its errors to one line.
    Returns the image (None if undecodable) and the diagnostic lines (OpenCV's log prefix
    removed)."""
    sys.stderr.flush()
    lines: list[str] = []
    with tempfile.TemporaryFile() as captured:
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)
        try:
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error as err:  # e.g. a header claiming more pixels than OpenCV allows
            img = None
            lines.append(str(err).strip().splitlines()[-1])
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read(4096).decode("utf-8", "replace")
    stripped = (re.sub(r"^\[ *\w+:[^\]]*\]\s*(global\s+\S+\s+\S+\s+)?", "", ln).strip() for ln in text.splitlines())
    return img, [ln for ln in stripped if ln] + lines


def _corrupt(diagnostics: list[str]) -> str | None:
    """The first diagnostic that means the decoded pixels are not the stream's (libjpeg fills
    what it could not decode with grey); None for benign ones (libpng warnings, extraneous
    bytes between JPEG segments, which some cameras write)."""
    for line in diagnostics:
        if ("Corrupt JPEG data" in line and "extraneous bytes" not in line) or "Premature end of JPEG" in line:
            return line
    return None


def decode_compressed(msg: Any, topic: str = "", expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A sensor_msgs CompressedImage (png or jpeg) -> (H, W, 3) uint8 RGB.

    ``expected_size`` (width, height) [px] rejects an image of another size, before
    decoding when the stream's header gives its size. A stream the codec reports as
    corrupt (even one it could partly decode) raises LogError with the codec's message.
    """
    fmt = str(msg.format)
    if compressed_codec(fmt) is None:
        raise LogError(
            f"topic {topic!r}: unsupported compressed image format {fmt!r} "
            f"(supported: {', '.join(COMPRESSED_FORMATS)})"
        )
    data = bytes(msg.data)
    header = stream_size(data)
    if header is not None:
        _check_size(header[1], header[2], expected_size, topic, f"{header[0]} image")
    cv2 = _cv2()
    img, diagnostics = _imdecode(cv2, data)
    problem = diagnostics[0] if img is None and diagnostics else _corrupt(diagnostics)
    if img is None or problem:
        why = f": {problem}" if problem else ""
        raise LogError(
            f"topic {topic!r}: {len(data)} bytes do not decode as {fmt!r}{why} (expected a valid png or jpeg stream)"
        )
    _check_size(img.shape[1], img.shape[0], expected_size, topic, "decoded image")
    if (img.ndim == 3 and img.shape[2] not in (3, 4)) or img.dtype not in (np.uint8, np.uint16):
        channels = img.shape[2] if img.ndim == 3 else 1
        raise LogError(
            f"topic {topic!r}: decoded image has {channels} channels of {img.dtype} "
            "(expected 1, 3 or 4 channels of 8 or 16 bits)"
        )
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    # OpenCV decodes to BGR(A) order.
    return np.ascontiguousarray(img[:, :, 2::-1])


# --- encoders (used by the log writer and the simulator) -------------------------------


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.dtype} {rgb.shape}")
    return np.ascontiguousarray(rgb)


def encode_raw(image: np.ndarray, encoding: str = "rgb8") -> dict[str, Any]:
    """Fields of a raw sensor_msgs Image (without header) for ``image``.

    ``rgb8``/``bgr8`` take (H, W, 3) uint8 RGB (``bgr8`` reorders the channels);
    ``mono8`` takes (H, W) uint8; ``mono16`` (H, W) uint16; ``32FC1`` takes (H, W) float depth [m]; ``16UC1`` takes
    (H, W) float depth [m] and stores whole millimetres.
    """
    if encoding in ("rgb8", "bgr8"):
        rgb = _check_rgb(image)
        arr = rgb if encoding == "rgb8" else np.ascontiguousarray(rgb[:, :, ::-1])
    elif encoding == "mono8":
        arr = np.asarray(image)
        if arr.dtype != np.uint8 or arr.ndim != 2:
            raise ValueError(f"mono8 needs an (H, W) uint8 image, got {arr.dtype} {arr.shape}")
    elif encoding == "mono16":
        arr = np.asarray(image)
        if arr.dtype != np.uint16 or arr.ndim != 2:
            raise ValueError(f"mono16 needs an (H, W) uint16 image, got {arr.dtype} {arr.shape}")
        arr = np.ascontiguousarray(arr, dtype="<u2")
    elif encoding == "32FC1":
        arr = np.asarray(image)
        if arr.ndim != 2:
            raise ValueError(f"32FC1 needs an (H, W) depth image, got shape {arr.shape}")
        arr = np.ascontiguousarray(arr, dtype="<f4")
    elif encoding == "16UC1":
        arr = np.asarray(image, dtype=np.float64)
        if arr.ndim != 2:
            raise ValueError(f"16UC1 needs an (H, W) depth image, got shape {arr.shape}")
        arr = np.ascontiguousarray(np.clip(np.round(arr * 1e3), 0, 65535), dtype="<u2")
    else:
        raise ValueError(f"cannot encode {encoding!r}; use rgb8, bgr8, mono8, mono16, 32FC1 or 16UC1")
    height, width = arr.shape[:2]
    return {
        "height": height,
        "width": width,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": arr.nbytes // height if height else 0,
        "data": arr.tobytes(),
    }


def encode_compressed(rgb: np.ndarray, fmt: str = "png", jpeg_quality: int = 95) -> dict[str, Any]:
    """Fields of a sensor_msgs CompressedImage (without header) for an (H, W, 3) uint8 RGB image.

    ``fmt`` is ``png`` (lossless) or ``jpeg`` (``jpeg_quality`` 0-100).
    """
    rgb = _check_rgb(rgb)
    cv2 = _cv2()
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    if fmt == "png":
        ok, buf = cv2.imencode(".png", bgr)
    elif fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [int(cv2.IMWRITE_JPEG_QUALITY), int(jpeg_quality)])
    else:
        raise ValueError(f"compressed format must be 'png' or 'jpeg', not {fmt!r}")
    if not ok:  # pragma: no cover - OpenCV fails only on invalid input checked above
        raise ValueError(f"OpenCV could not encode a {rgb.shape} image as {fmt}")
    # image_transport's format string: source encoding; codec compressed output encoding.
    return {"format": f"rgb8; {fmt} compressed bgr8", "data": buf.tobytes()}


def encode_mask_png(labels: np.ndarray) -> dict[str, Any]:
    """Fields of a sensor_msgs CompressedImage (without header) for a recorded object mask:
    (H, W) uint8 or uint16 labels as a one-channel png (``format`` ``"mono8; png compressed"``
    or ``"mono16; png compressed"``, as image_transport writes)."""
    arr = np.asarray(labels)
    if arr.ndim != 2 or arr.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"a png mask needs an (H, W) uint8 or uint16 image, got {arr.dtype} {arr.shape}")
    ok, buf = _cv2().imencode(".png", np.ascontiguousarray(arr))
    if not ok:  # pragma: no cover - OpenCV fails only on invalid input checked above
        raise ValueError(f"OpenCV could not encode a {arr.shape} mask as png")
    depth = "mono8" if arr.dtype == np.uint8 else "mono16"
    return {"format": f"{depth}; png compressed", "data": buf.tobytes()}
