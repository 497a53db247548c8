"""Image decoding and encoding: exact round trips for raw and png, close for jpeg, clear errors."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mvtop_cli.errors import LogError
from mvtop_cli.io.images import (
    compressed_codec,
    decode_depth,
    decode_image,
    encode_compressed,
    encode_raw,
)


def msg(**fields) -> SimpleNamespace:
    return SimpleNamespace(**fields)


@pytest.fixture
def rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (12, 17, 3), dtype=np.uint8)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_raw_colour_round_trip_is_exact(rgb, encoding):
    fields = encode_raw(rgb, encoding)
    assert fields["step"] == 17 * 3 and len(fields["data"]) == 12 * 17 * 3
    np.testing.assert_array_equal(decode_image(msg(**fields)), rgb)


def test_bgr8_really_swaps_channels(rgb):
    data = encode_raw(rgb, "bgr8")["data"]
    assert np.frombuffer(data, np.uint8).reshape(12, 17, 3)[0, 0].tolist() == rgb[0, 0, ::-1].tolist()


def test_mono8_expands_to_three_channels():
    gray = np.arange(20, dtype=np.uint8).reshape(4, 5)
    out = decode_image(msg(**encode_raw(gray, "mono8")))
    assert out.shape == (4, 5, 3)
    np.testing.assert_array_equal(out[:, :, 1], gray)


def test_rgba_bgra_mono16_and_row_padding():
    px = np.array([[[10, 20, 30, 255], [40, 50, 60, 0]]], dtype=np.uint8)  # 1x2 RGBA
    out = decode_image(msg(height=1, width=2, encoding="rgba8", is_bigendian=0, step=8, data=px.tobytes()))
    assert out.tolist() == [[[10, 20, 30], [40, 50, 60]]]
    out = decode_image(msg(height=1, width=2, encoding="bgra8", is_bigendian=0, step=8, data=px.tobytes()))
    assert out.tolist() == [[[30, 20, 10], [60, 50, 40]]]
    m16 = np.array([[0x1234, 0xFF00]], dtype="<u2")
    out = decode_image(msg(height=1, width=2, encoding="mono16", is_bigendian=0, step=4, data=m16.tobytes()))
    assert out[0, :, 0].tolist() == [0x12, 0xFF]
    be = np.array([[0x1234, 0xFF00]], dtype=">u2")
    out = decode_image(msg(height=1, width=2, encoding="mono16", is_bigendian=1, step=4, data=be.tobytes()))
    assert out[0, :, 0].tolist() == [0x12, 0xFF]
    # rows padded to 8 bytes: the padding is dropped
    padded = bytes([1, 2, 3, 4, 5, 6, 0, 0, 7, 8, 9, 10, 11, 12, 0, 0])
    out = decode_image(msg(height=2, width=2, encoding="rgb8", is_bigendian=0, step=8, data=padded))
    assert out.reshape(-1).tolist() == list(range(1, 13))


def test_depth_round_trips():
    depth = np.random.default_rng(1).uniform(0, 0.003, (6, 9)).astype(np.float32)
    out = decode_depth(msg(**encode_raw(depth, "32FC1")))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, depth)
    mm = decode_depth(msg(**encode_raw(np.full((2, 3), 1.2345), "16UC1")))
    np.testing.assert_allclose(mm, 1.234, atol=1e-6)  # whole millimetres


def test_png_round_trip_is_exact(rgb):
    fields = encode_compressed(rgb, "png")
    assert fields["format"] == "rgb8; png compressed bgr8" and compressed_codec(fields["format"]) == "png"
    np.testing.assert_array_equal(decode_image(msg(**fields)), rgb)


def test_jpeg_round_trip_is_close():
    # jpeg is lossy: use a smooth image and compare the mean error
    yy, xx = np.mgrid[0:32, 0:48]
    smooth = np.stack([xx * 5, yy * 7, (xx + yy) * 3], axis=-1).astype(np.uint8)
    out = decode_image(msg(**encode_compressed(smooth, "jpeg", jpeg_quality=95)))
    assert out.shape == smooth.shape
    assert np.abs(out.astype(int) - smooth.astype(int)).mean() < 3.0
    # colour order survives (a red image stays red)
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 200
    out = decode_image(msg(**encode_compressed(red, "jpeg")))
    assert out[..., 0].mean() > 190 and out[..., 2].mean() < 10


def test_unknown_encoding_names_topic_and_lists_supported():
    m = msg(height=1, width=1, encoding="yuv422", is_bigendian=0, step=2, data=b"\0\0")
    with pytest.raises(
        LogError,
        match=r"topic '/cameras/front/image': unsupported colour image encoding 'yuv422' "
        r"\(supported: rgb8, bgr8, rgba8, bgra8, mono8",
    ):
        decode_image(m, "/cameras/front/image")
    with pytest.raises(LogError, match=r"unsupported depth image encoding 'rgb8' \(supported: 32FC1, 16UC1\)"):
        decode_depth(msg(**encode_raw(np.zeros((2, 2, 3), np.uint8))), "/tactile/left/depth")


def test_size_mismatch_is_reported():
    m = msg(height=4, width=5, encoding="rgb8", is_bigendian=0, step=15, data=bytes(59))
    with pytest.raises(
        LogError,
        match=r"topic '/img': rgb8 image of 5x4 has step 15 and 59 data bytes "
        r"\(expected step >= 15 and step\*height = 60 bytes\)",
    ):
        decode_image(m, "/img")
    m = msg(height=2, width=5, encoding="rgb8", is_bigendian=0, step=10, data=bytes(20))
    with pytest.raises(LogError, match=r"expected step >= 15"):
        decode_image(m, "/img")


def test_bad_compressed_data_and_formats():
    with pytest.raises(LogError, match=r"topic '/c': 7 bytes do not decode as 'png'"):
        decode_image(msg(format="png", data=b"notapng"), "/c")
    with pytest.raises(LogError, match=r"unsupported compressed image format 'h264' \(supported: png, jpeg\)"):
        decode_image(msg(format="h264", data=b""), "/c")
    with pytest.raises(LogError, match=r"compressed depth .* is not supported"):
        decode_depth(msg(format="16UC1; compressedDepth png", data=b""), "/d")


def test_encoders_reject_wrong_input():
    with pytest.raises(ValueError, match="uint8 RGB"):
        encode_raw(np.zeros((2, 2)), "rgb8")
    with pytest.raises(ValueError, match="cannot encode 'yuv422'"):
        encode_raw(np.zeros((2, 2, 3), np.uint8), "yuv422")
    with pytest.raises(ValueError, match="'png' or 'jpeg'"):
        encode_compressed(np.zeros((2, 2, 3), np.uint8), "webp")
