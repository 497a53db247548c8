"""Decode sensor_msgs Image / CompressedImage messages to numpy arrays, and encode them back.

Colour images come out as (H, W, 3) uint8 RGB (mono is expanded to three channels,
16-bit mono is scaled to 8 bits); depth images as (H, W) float32 [m]. OpenCV is imported
when first needed (only for compressed images).
"""

from __future__ import annotations

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


def decode_image(msg: Any, topic: str = "") -> np.ndarray:
    """A sensor_msgs Image or CompressedImage -> (H, W, 3) uint8 RGB.

    Raw encodings: rgb8, bgr8, rgba8, bgra8, mono8, mono16 (scaled to 8 bits), 8UC1, 8UC3.
    Compressed formats: png and jpeg (any ``format`` string naming them, as
    image_transport writes e.g. ``"rgb8; jpeg compressed bgr8"``).
    """
    if hasattr(msg, "format"):
        return decode_compressed(msg, topic)
    arr, encoding = _raw_array(msg, topic, COLOR_ENCODINGS, "colour")
    return _to_rgb(arr, encoding)


def decode_depth(msg: Any, topic: str = "") -> np.ndarray:
    """A sensor_msgs Image with encoding 32FC1 [m] or 16UC1 [mm] -> (H, W) float32 [m]."""
    if hasattr(msg, "format"):
        raise LogError(
            f"topic {topic!r}: compressed depth ({msg.format!r}) is not supported "
            "(expected a raw sensor_msgs/msg/Image with encoding 32FC1 or 16UC1)"
        )
    arr, encoding = _raw_array(msg, topic, DEPTH_ENCODINGS, "depth")
    if encoding == "16UC1":
        return (arr[:, :, 0].astype(np.float32) * np.float32(1e-3)).astype(np.float32)
    return arr[:, :, 0].astype(np.float32)


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


def decode_compressed(msg: Any, topic: str = "") -> np.ndarray:
    """A sensor_msgs CompressedImage (png or jpeg) -> (H, W, 3) uint8 RGB."""
    fmt = str(msg.format)
    if compressed_codec(fmt) is None:
        raise LogError(
            f"topic {topic!r}: unsupported compressed image format {fmt!r} "
            f"(supported: {', '.join(COMPRESSED_FORMATS)})"
        )
    cv2 = _cv2()
    img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise LogError(
            f"topic {topic!r}: {len(msg.data)} bytes do not decode as {fmt!r} (expected a valid png or jpeg stream)"
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
    ``mono8`` takes (H, W) uint8; ``32FC1`` takes (H, W) float depth [m]; ``16UC1`` takes
    (H, W) float depth [m] and stores whole millimetres.
    """
    if encoding in ("rgb8", "bgr8"):
        rgb = _check_rgb(image)
        arr = rgb if encoding == "rgb8" else np.ascontiguousarray(rgb[:, :, ::-1])
    elif encoding == "mono8":
        arr = np.asarray(image)
        if arr.dtype != np.uint8 or arr.ndim != 2:
            raise ValueError(f"mono8 needs an (H, W) uint8 image, got {arr.dtype} {arr.shape}")
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
        raise ValueError(f"cannot encode {encoding!r}; use rgb8, bgr8, mono8, 32FC1 or 16UC1")
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
