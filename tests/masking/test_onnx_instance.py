"""Instance-segmentation ONNX backend: class and score filtering, letterbox round trips,
per-box masks and model checks, on tiny models built in the tests (onnx_models.py)."""

import cv2
import numpy as np
import onnx_models
import pytest

from mvtop_cli.errors import ConfigError, ModelError
from mvtop_cli.masking.base import MaskContext, get_backend
from mvtop_cli.masking.onnx_instance import InstanceOnnxBackend, InstanceOnnxOptions


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("instance")
    return {
        "dynamic": onnx_models.instance_model(d / "dynamic.onnx"),
        "fixed": onnx_models.instance_model(d / "fixed.onnx", fixed_hw=(320, 320)),
        "fixed_wide": onnx_models.instance_model(d / "fixed_wide.onnx", fixed_hw=(256, 384)),
        "boxes": onnx_models.box_mask_model(
            d / "boxes.onnx", (320, 320), boxes=[[10, 20, 110, 70], [200, 100, 260, 180]], labels=[1, 1],
            scores=[0.7, 0.95],
        ),
    }


def disc(shape, centre, radius):
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2


def scene(width, height):
    """A red disc (class 1, score 0.9 in the model) and a green disc (class 2, score 0.6)."""
    img = np.full((height, width, 3), 40, np.uint8)
    r = min(width, height)
    a = disc(img.shape[:2], (0.3 * width, 0.35 * height), 0.12 * r)
    b = disc(img.shape[:2], (0.7 * width, 0.65 * height), 0.16 * r)
    img[a], img[b] = (255, 0, 0), (0, 255, 0)
    return img, a, b


def within_one_pixel(mask, truth):
    k = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(truth.astype(np.uint8), k).astype(bool)
    shrunk = cv2.erode(truth.astype(np.uint8), k).astype(bool)
    return not np.any(mask & ~grown) and not np.any(shrunk & ~mask)


def backend(models, name="dynamic", **options):
    options.setdefault("num_threads", 1)
    return InstanceOnnxBackend(model_path=models[name], **options)


def test_class_id_and_score_threshold_filter_instances(models):
    img, a, b = scene(320, 240)
    props = backend(models, class_id=None).proposals(img)
    assert len(props) == 2 and np.array_equal(props[0], a) and np.array_equal(props[1], b)  # best score first
    (only_a,) = backend(models, class_id=1).proposals(img)
    assert np.array_equal(only_a, a)
    (only_b,) = backend(models, class_id=2).proposals(img)
    assert np.array_equal(only_b, b)
    assert backend(models, class_id=2, score_threshold=0.7).proposals(img) == []
    assert len(backend(models, class_id=None, score_threshold=0.7).proposals(img)) == 1
    assert backend(models, class_id=7).proposals(img) == []


def test_detections_carry_labels_scores_and_boxes(models):
    img, _, _ = scene(320, 240)
    det = backend(models, class_id=None).detect(img)
    assert det.labels.tolist() == [1, 2] and np.allclose(det.scores, [0.9, 0.6])
    assert det.boxes.shape == (2, 4) and det.masks.shape == (2, 240, 320)


@pytest.mark.parametrize("width,height", [(640, 480), (320, 240), (480, 640), (1280, 720), (333, 517)])
@pytest.mark.parametrize("name", ["fixed", "fixed_wide"])
def test_letterbox_round_trip_is_exact_to_a_pixel(models, name, width, height):
    """A fixed-size model sees the image resized and padded; its masks come back in image pixels."""
    img, a, b = scene(width, height)
    props = backend(models, name, class_id=None).proposals(img)
    assert len(props) == 2
    assert within_one_pixel(props[0], a) and within_one_pixel(props[1], b)


def test_preprocess_layouts(models):
    img = np.zeros((100, 200, 3), np.uint8)
    img[..., 0] = 255
    x, frame = backend(models).preprocess(img)
    assert x.shape == (3, 100, 200) and np.allclose(x[0], 1.0) and np.allclose(x[1:], 0.0)
    x, frame = backend(models, "fixed").preprocess(img)
    assert x.shape == (1, 3, 320, 320) and (frame.resized_h, frame.resized_w) == (160, 320)
    assert np.allclose(x[0, 0, :160], 1.0) and np.all(x[0, :, 160:] == 0)
    x, _ = backend(models, channel_order="bgr", pixel_mean=(0.5, 0.5, 0.5), pixel_std=(0.5, 0.5, 0.5)).preprocess(img)
    assert np.allclose(x[2], 1.0) and np.allclose(x[:2], -1.0)


def test_dynamic_model_with_input_size_resizes(models):
    img, a, b = scene(1280, 720)
    x, frame = backend(models, input_size=320).preprocess(img)
    assert x.shape == (3, 180, 320)
    props = backend(models, input_size=320, class_id=1).proposals(img)
    assert len(props) == 1 and within_one_pixel(props[0], a)


def test_per_box_masks_are_pasted_into_their_boxes(models):
    """28 x 28 masks relative to boxes in the 320 x 320 input map to the boxes in image pixels."""
    img = np.zeros((480, 640, 3), np.uint8)  # input scale 0.5
    props = backend(models, "boxes").proposals(img)
    assert len(props) == 2
    for mask, (x0, y0, x1, y1) in zip(props, [(400, 200, 520, 360), (20, 40, 220, 140)]):
        expected = np.zeros((480, 640), bool)
        expected[y0:y1, x0:x1] = True
        assert np.array_equal(mask, expected)


def test_roi_limits_proposals_and_prompt_picks_overlapping_instance(models):
    img, a, b = scene(320, 240)
    b_only = backend(models, class_id=None)
    props = b_only.proposals(img, MaskContext(roi_box=(150, 100, 320, 240)))
    assert len(props) == 1 and np.array_equal(props[0], b)  # disc a lies outside the window
    shifted = np.roll(b, 5, axis=1)
    assert np.array_equal(b_only.prompt(img, shifted), b)
    assert np.array_equal(b_only.prompt(img, np.array([[96.0, 84.0]])), a)
    assert not b_only.prompt(img, np.array([[5.0, 5.0]])).any()


def test_detections_are_cached_by_image_content(models):
    b = backend(models, class_id=None)
    calls = []
    run = b.model.run
    b.model.run = lambda *args, **kw: calls.append(1) or run(*args, **kw)
    img, _, _ = scene(320, 240)
    b.proposals(img)
    b.prompt(img.copy(), np.array([[96.0, 84.0]]))
    assert len(calls) == 1


def test_registry(models):
    b = get_backend("instance_onnx", model_path=str(models["dynamic"]), class_id=2, num_threads=1)
    assert isinstance(b, InstanceOnnxBackend) and b.options.class_id == 2


def test_bad_models(tmp_path):
    with pytest.raises(ModelError, match=r"missing.onnx: instance segmentation model not found"):
        InstanceOnnxBackend(model_path=tmp_path / "missing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00\x01garbage")
    with pytest.raises(ModelError, match=r"junk.onnx: cannot load instance segmentation model as an ONNX model"):
        InstanceOnnxBackend(model_path=junk)
    hwc = onnx_models.signature_model(
        tmp_path / "hwc.onnx", {"image": ["H", "W", 3]},
        {"boxes": ["N", 4], "labels": ["N"], "scores": ["N"], "masks": ["N", 1, "h", "w"]},
    )
    with pytest.raises(
        ModelError,
        match=r"hwc.onnx: instance segmentation model: expected input image\[3,H,W\] or image\[1,3,H,W\] float32; "
        r"got image\[\?,\?,3\]",
    ):
        InstanceOnnxBackend(model_path=hwc)
    no_masks = onnx_models.signature_model(
        tmp_path / "det.onnx", {"image": [3, "H", "W"]}, {"boxes": ["N", 4], "scores": ["N"]}
    )
    with pytest.raises(
        ModelError,
        match=r"det.onnx: instance segmentation model: expected outputs boxes, labels, scores, masks; "
        r"got boxes\[.,4\], scores\[.\]$",
    ):
        InstanceOnnxBackend(model_path=no_masks)


def test_options():
    with pytest.raises(ConfigError, match=r"unknown option 'score_treshold' \(did you mean 'score_threshold'\?\)"):
        InstanceOnnxOptions.from_mapping({"model_path": "m.onnx", "score_treshold": 0.3})
    with pytest.raises(ConfigError, match="model_path' is required"):
        InstanceOnnxOptions.from_mapping({})
    with pytest.raises(ConfigError, match=r"score_threshold=1.5"):
        InstanceOnnxOptions.from_mapping({"model_path": "m.onnx", "score_threshold": 1.5})
    o = InstanceOnnxOptions.from_mapping(
        {"model_path": "m.onnx", "class_id": None, "providers": ["CPUExecutionProvider"]}
    )
    assert o.class_id is None and o.providers == ("CPUExecutionProvider",)
