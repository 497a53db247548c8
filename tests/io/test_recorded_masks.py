"""Object masks recorded in the log by an external segmenter: decoding, and pairing with
their camera images by stamp (``SensorImage.mask``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mvtop_cli.errors import LogError
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.io.frames import FrameReader, LogTopics, SensorTopics
from mvtop_cli.io.images import decode_mask, encode_compressed, encode_mask_png, encode_raw
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
W, H = 32, 24


def _labels(k: int = 0) -> np.ndarray:
    labels = np.zeros((H, W), np.uint8)
    labels[5 + k : 15 + k, 8:20] = 7
    labels[0:3, 0:3] = 2  # another object of the segmenter
    return labels


def _raw(labels: np.ndarray, encoding: str):
    return SimpleNamespace(**encode_raw(labels, encoding))


def test_decodes_mono8_mono16_and_png():
    labels = _labels()
    assert np.array_equal(decode_mask(_raw(labels, "mono8")), labels)
    wide = labels.astype(np.uint16) * 1000
    assert np.array_equal(decode_mask(_raw(wide, "mono16")), wide)
    for arr in (labels, wide):
        out = decode_mask(SimpleNamespace(**encode_mask_png(arr)), "/m", (W, H))
        assert out.dtype == np.uint16 and np.array_equal(out, arr)


@pytest.mark.parametrize("msg, what", [
    (SimpleNamespace(**encode_raw(np.zeros((H, W, 3), np.uint8), "rgb8")), "mask encoding 'rgb8' is not supported"),
    (SimpleNamespace(**encode_compressed(np.zeros((H, W, 3), np.uint8), "jpeg")), "mask in compressed format"),
    (SimpleNamespace(**encode_compressed(np.zeros((H, W, 3), np.uint8), "png")), "png mask has 3 channels"),
])
def test_wrong_encodings_give_one_line_naming_the_topic(msg, what):
    with pytest.raises(LogError) as info:
        decode_mask(msg, "/front/mask")
    text = str(info.value)
    assert text.startswith("topic '/front/mask': ") and what in text and "\n" not in text
    assert "expected a mask as sensor_msgs/Image mono8 or mono16, or a one-channel png CompressedImage" in text


def test_a_mask_of_another_size_is_rejected():
    with pytest.raises(LogError, match=r"topic '/m': mono8 mask of 32x24 px but CameraInfo says 64x48"):
        decode_mask(_raw(_labels(), "mono8"), "/m", (64, 48))


def _log(path, *, mask_topic: str | None = "/front/mask", fmt: str = "raw", drop: int | None = None,
         offset_ms: int = 3, encoding: str | None = None) -> None:
    cam = PinholeCamera(width=W, height=H, K=np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]))
    with LogWriter(path) as log:
        log.write_tf([("world", "front_optical", np.eye(4))], T0, static=True)
        for k in range(4):
            t = T0 + k * 100 * MS
            log.write_tf([("world", "ee", np.eye(4))], t)
            log.write_camera_info("/front/camera_info", cam, t, "front_optical")
            log.write_compressed_image("/front/image/compressed", np.full((H, W, 3), 40 * k, np.uint8), t,
                                       "front_optical", fmt="png")
            if mask_topic is not None and k != drop:
                if encoding is not None:
                    log.write_image(mask_topic, np.zeros((H, W, 3), np.uint8), t, "front_optical", encoding=encoding)
                else:
                    log.write_mask(mask_topic, _labels(k), t + offset_ms * MS, "front_optical", fmt=fmt)


def _frames(path, mask_topic="/front/mask"):
    sensors = [SensorTopics("front", "camera", "/front/image/compressed", "/front/camera_info",
                            mask_topic=mask_topic)]
    with McapLog(path) as log:
        reader = FrameReader(log, sensors, LogTopics(sync_tolerance_ns=10 * MS))
        return list(reader), reader.skipped


@pytest.mark.parametrize("fmt, topic", [("raw", "/front/mask"), ("png", "/front/mask/compressed")])
def test_each_image_carries_the_mask_recorded_within_the_sync_tolerance(tmp_path, fmt, topic):
    _log(tmp_path / "a.mcap", mask_topic=topic, fmt=fmt)
    frames, skipped = _frames(tmp_path / "a.mcap", topic)
    assert len(frames) == 4 and skipped == []
    for k, f in enumerate(frames):
        img = f.cameras["front"]
        assert img.stamp_ns == T0 + k * 100 * MS  # the frame's time is the image's, not the mask's
        assert np.array_equal(img.mask, _labels(k))


def test_an_image_without_its_mask_is_skipped_and_listed(tmp_path):
    _log(tmp_path / "a.mcap", drop=2)
    frames, skipped = _frames(tmp_path / "a.mcap")
    assert [f.index for f in frames] == [0, 1, 2]  # the third image had no mask
    assert [f.stamp_ns for f in frames] == [T0, T0 + 100 * MS, T0 + 300 * MS]
    assert skipped[0][0] == T0 + 200 * MS and "front: no mask on '/front/mask' within the sync tolerance" in \
        skipped[0][1]


def test_a_mask_outside_the_sync_tolerance_does_not_pair(tmp_path):
    _log(tmp_path / "a.mcap", offset_ms=30)
    frames, skipped = _frames(tmp_path / "a.mcap")
    assert frames == [] and len([s for s in skipped if "no mask" in s[1]]) == 4


def test_missing_mask_topic_is_one_line(tmp_path):
    _log(tmp_path / "a.mcap", mask_topic=None)
    with pytest.raises(LogError) as info:
        _frames(tmp_path / "a.mcap")
    assert str(info.value) == (f"{tmp_path / 'a.mcap'}: topic '/front/mask' not found (expected sensor_msgs/msg/Image "
                               "or sensor_msgs/msg/CompressedImage for the object masks of 'front')")


def test_wrong_mask_encoding_in_a_log_is_one_line(tmp_path):
    _log(tmp_path / "a.mcap", encoding="rgb8")
    with pytest.raises(LogError) as info:
        _frames(tmp_path / "a.mcap")
    text = str(info.value)
    assert "topic '/front/mask': mask encoding 'rgb8' is not supported" in text and "\n" not in text
    assert text.startswith(str(tmp_path / "a.mcap"))
