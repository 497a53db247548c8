"""SAM ONNX backend: coordinate round trips, automatic proposals, prompts and model checks
on tiny encoder/decoder models built in the tests (tests/masking/onnx_models.py)."""

import cv2
import numpy as np
import onnx_models
import pytest

from mvtop_cli.bitmasks import iou_matrix
from mvtop_cli.errors import ConfigError, ModelError
from mvtop_cli.masking.base import MaskContext, PromptableMaskBackend, get_backend
from mvtop_cli.masking.onnx_common import ResizeFrame, remove_small_regions, stability_score
from mvtop_cli.masking.onnx_sam import SamOnnxBackend, SamOnnxOptions, grid_points, interior_points

RED, GREEN, BACKGROUND = (255, 0, 0), (0, 255, 0), 40


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("sam")
    return {
        "encoder": onnx_models.sam_encoder(d / "encoder.onnx"),
        "decoder": onnx_models.sam_decoder(d / "decoder.onnx"),
        "decoder_multi": onnx_models.sam_decoder(d / "decoder_multi.onnx", multimask=True),
        "decoder_soft": onnx_models.sam_decoder(d / "decoder_soft.onnx", logit_scale=0.05),
        "encoder_512": onnx_models.sam_encoder(d / "encoder_512.onnx", input_size=512, embed_side=32),
        "decoder_512": onnx_models.sam_decoder(d / "decoder_512.onnx", input_size=512, embed_side=32),
    }


def backend(models, encoder="encoder", decoder="decoder", **options):
    options.setdefault("num_threads", 1)
    options.setdefault("points_per_side", 8)
    return SamOnnxBackend(encoder_path=models[encoder], decoder_path=models[decoder], **options)


def disc(shape, centre, radius):
    """(H, W) bool disc of pixels whose centres are within ``radius`` of ``centre`` (x, y)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2


def scene(width, height, a, b):
    """Image with a red disc ``a`` and a green disc ``b``, each ((x, y), radius) in pixels,
    and their masks."""
    img = np.full((height, width, 3), BACKGROUND, np.uint8)
    mask_a, mask_b = disc(img.shape[:2], *a), disc(img.shape[:2], *b)
    img[mask_a], img[mask_b] = RED, GREEN
    return img, mask_a, mask_b


def within_one_pixel(mask, truth):
    """Every pixel of ``mask`` within 1 px of ``truth`` and ``truth`` shrunk by 1 px inside ``mask``."""
    k = np.ones((3, 3), np.uint8)
    grown = cv2.dilate(truth.astype(np.uint8), k).astype(bool)
    shrunk = cv2.erode(truth.astype(np.uint8), k).astype(bool)
    return not np.any(mask & ~grown) and not np.any(shrunk & ~mask)


SIZES = [(640, 480), (320, 240), (480, 640), (1280, 720), (333, 517)]


def objects_for(width, height):
    """Disc A and disc B placed relative to the image size."""
    r = min(width, height)
    return ((0.3 * width, 0.35 * height), 0.12 * r), ((0.7 * width, 0.65 * height), 0.16 * r)


@pytest.mark.parametrize("width,height", SIZES)
def test_point_prompt_round_trip_is_exact_to_a_pixel(models, width, height):
    """A prompt point goes image -> 1024 frame -> decoder -> mask in image pixels: the
    decoder's 6 px disc around it lands where the point was."""
    img, _, _ = scene(width, height, *objects_for(width, height))
    b = backend(models)
    for x, y in [(5.0, 5.0), (width - 7.0, 0.5 * height), (0.5 * width, height - 8.0)]:
        mask = b.prompt(img, np.array([[x, y]]))
        assert within_one_pixel(mask, disc(img.shape[:2], (x, y), 6.0)), (x, y)


@pytest.mark.parametrize("width,height", SIZES)
def test_image_round_trip_is_exact_to_a_pixel(models, width, height):
    """The image goes through the encoder's resize and padding; the disc the decoder draws
    from the encoded centroid matches the disc in the image."""
    a, bb = objects_for(width, height)
    img, mask_a, mask_b = scene(width, height, a, bb)
    b = backend(models)
    assert within_one_pixel(b.prompt(img, np.array([a[0]])), mask_a)
    assert within_one_pixel(b.prompt(img, np.array([bb[0]])), mask_b)


def test_preprocess_resizes_long_side_normalises_and_pads(models):
    b = backend(models)
    img = np.zeros((300, 600, 3), np.uint8)
    img[:, :, 0] = 255
    x, frame = b.preprocess(img)
    assert x.shape == (1, 3, 1024, 1024) and x.dtype == np.float32
    assert (frame.resized_h, frame.resized_w) == (512, 1024)
    np.testing.assert_allclose(
        x[0, :, :512, :].mean(axis=(1, 2)), [(255 - 123.675) / 58.395, -116.28 / 57.12, -103.53 / 57.375], rtol=1e-5
    )
    assert np.all(x[0, :, 512:, :] == 0)


def test_resize_frame_maps_points_both_ways():
    f = ResizeFrame.fit((480, 640), (1024, 1024))
    assert (f.resized_h, f.resized_w) == (768, 1024)
    pts = np.array([[0.0, 0.0], [639.0, 479.0], [123.4, 56.7]])
    np.testing.assert_allclose(f.to_image(f.to_input(pts)), pts)
    np.testing.assert_allclose(f.to_input(pts)[1], [639 * 1.6, 479 * 1.6])


def test_proposals_find_both_discs(models):
    img, mask_a, mask_b = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    props = backend(models).proposals(img)
    assert len(props) == 2
    assert all(p.shape == (480, 640) and p.dtype == bool for p in props)
    found = iou_matrix(np.stack(props), np.stack([mask_a, mask_b]), empty_score=0.0)
    assert found.max(axis=0).min() > 0.97
    assert within_one_pixel(props[int(np.argmax(found[:, 0]))], mask_a)


def test_nms_removes_duplicate_proposals(models):
    """Every grid point inside a disc gives the same mask; NMS keeps one per disc."""
    img, mask_a, mask_b = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    dup = backend(models, nms_iou_thresh=1.0, max_proposals=100).proposals(img)
    inside = sum(int(mask_a[int(y), int(x)] or mask_b[int(y), int(x)]) for x, y in grid_points(8) * [640, 480])
    assert len(dup) == inside > 2
    assert len(backend(models).proposals(img)) == 2


def test_low_predicted_iou_and_unstable_masks_are_dropped(models):
    img, _, _ = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    # Misses (6 px discs, iou 0.2) pass only when the IoU threshold lets them (and the
    # stability threshold: +-1 logit moves their edge by 0.1 px, 7 % of their area).
    loose = dict(min_mask_area_px=10, nms_iou_thresh=0.5, max_proposals=100, stability_score_thresh=0.9)
    assert len(backend(models, **loose).proposals(img)) == 2
    assert len(backend(models, pred_iou_thresh=0.1, **loose).proposals(img)) > 2
    assert len(backend(models, pred_iou_thresh=0.1, **{**loose, "stability_score_thresh": 0.95}).proposals(img)) == 2
    # Soft logits: thresholds +-1 give very different masks (unstable).
    assert backend(models, decoder="decoder_soft").proposals(img) == []
    assert len(backend(models, decoder="decoder_soft", stability_score_thresh=0.0).proposals(img)) == 2


def test_proposals_stay_in_roi(models):
    img, mask_a, _ = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    roi = (120, 70, 290, 240)
    for crop in (True, False):
        props = backend(models, crop_to_roi=crop).proposals(img, MaskContext(roi_box=roi))
        assert len(props) == 1, crop
        assert within_one_pixel(props[0], mask_a)
        outside = np.ones((480, 640), bool)
        outside[70:240, 120:290] = False
        assert not np.any(props[0] & outside)


def test_prompt_mask_returns_nearest_disc(models):
    img, mask_a, mask_b = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    b = backend(models)
    shifted = disc((480, 640), (212, 141), 48)  # the CAD silhouette at a slightly wrong pose
    assert within_one_pixel(b.prompt(img, shifted), mask_a)
    assert within_one_pixel(b.prompt(img, disc((480, 640), (440, 310), 75)), mask_b)
    assert within_one_pixel(backend(models, prompt_use_box=False, prompt_points=1).prompt(img, shifted), mask_a)
    assert not b.prompt(img, np.zeros((480, 640), bool)).any()
    assert not b.prompt(img, np.array([[-50.0, 20.0]])).any()


def test_prompt_picks_mask_with_best_predicted_iou(models):
    img, mask_a, _ = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    b = backend(models, decoder="decoder_multi")
    assert within_one_pixel(b.prompt(img, np.array([[200.0, 150.0]])), mask_a)  # 0.95 beats 0.5
    miss = b.prompt(img, np.array([[600.0, 50.0]]))  # 0.5 beats 0.2; both the small disc
    assert within_one_pixel(miss, disc((480, 640), (600, 50), 6))


def test_embedding_is_computed_once_per_image(models):
    b = backend(models)
    calls = []
    run = b.encoder.run
    b.encoder.run = lambda *a, **k: calls.append(1) or run(*a, **k)
    img, _, _ = scene(320, 240, ((100, 80), 30), ((220, 160), 40))
    b.proposals(img)
    b.prompt(img, np.array([[100.0, 80.0]]))
    b.prompt(img.copy(), np.array([[220.0, 160.0]]))  # same content, another array
    assert len(calls) == 1
    other = img.copy()
    other[0, 0] = 255
    b.prompt(other, np.array([[100.0, 80.0]]))
    assert len(calls) == 2


def test_input_size_and_mask_input_size_come_from_the_models(models):
    b = backend(models, encoder="encoder_512", decoder="decoder_512")
    assert (b.input_size, b.mask_input_size) == (512, 128)
    img, mask_a, _ = scene(640, 480, ((200, 150), 50), ((450, 300), 70))
    assert within_one_pixel(b.prompt(img, np.array([[200.0, 150.0]])), mask_a)
    with pytest.raises(ModelError, match=r"encoder_512.onnx: .*fixed at 512 px but option input_size is 1024"):
        backend(models, encoder="encoder_512", decoder="decoder_512", input_size=1024)


def test_registry_builds_a_promptable_backend(models):
    b = get_backend("sam_onnx", encoder_path=str(models["encoder"]), decoder_path=str(models["decoder"]), num_threads=1)
    assert isinstance(b, SamOnnxBackend) and isinstance(b, PromptableMaskBackend)


# -- bad models and options ------------------------------------------------------------------


def test_missing_model_file(models, tmp_path):
    with pytest.raises(ModelError, match=r"nope.onnx: SAM mask decoder not found"):
        SamOnnxBackend(encoder_path=models["encoder"], decoder_path=tmp_path / "nope.onnx")


def test_file_that_is_not_onnx(models, tmp_path):
    bad = tmp_path / "encoder.onnx"
    bad.write_text("not a model\n")
    with pytest.raises(ModelError, match=r"encoder.onnx: cannot load SAM image encoder as an ONNX model") as err:
        SamOnnxBackend(encoder_path=bad, decoder_path=models["decoder"])
    assert "\n" not in str(err.value)


def test_decoder_with_wrong_input_names(models, tmp_path):
    bad = onnx_models.sam_decoder(tmp_path / "decoder.onnx", rename={"point_coords": "coords"})
    with pytest.raises(ModelError) as err:
        SamOnnxBackend(encoder_path=models["encoder"], decoder_path=bad)
    msg = str(err.value)
    assert msg.startswith(
        f"{bad}: SAM mask decoder: expected inputs image_embeddings, point_coords, point_labels, mask_input"
    )
    assert "got " in msg and "coords[1,?,2]" in msg and "\n" not in msg


def test_decoder_without_iou_output(models, tmp_path):
    inputs = {
        "image_embeddings": [1, 256, 64, 64], "point_coords": [1, "n", 2], "point_labels": [1, "n"],
        "mask_input": [1, 1, 256, 256], "has_mask_input": [1], "orig_im_size": [2],
    }
    bad = onnx_models.signature_model(tmp_path / "d.onnx", inputs, {"masks": [1, 1, "h", "w"]})
    with pytest.raises(
        ModelError, match=r"d.onnx: SAM mask decoder: expected outputs masks, iou_predictions; got masks"
    ):
        SamOnnxBackend(encoder_path=models["encoder"], decoder_path=bad)


def test_encoder_with_wrong_signature_or_embedding_shape(models, tmp_path):
    two = onnx_models.signature_model(
        tmp_path / "e2.onnx", {"image": [1, 3, 1024, 1024], "x": [1]}, {"image_embeddings": [1, 256, 64, 64]}
    )
    with pytest.raises(ModelError, match=r"e2.onnx: SAM image encoder: expected one input image\[1,3,S,S\]; got 2"):
        SamOnnxBackend(encoder_path=two, decoder_path=models["decoder"])
    hwc = onnx_models.signature_model(
        tmp_path / "e3.onnx", {"image": [1024, 1024, 3]}, {"image_embeddings": [1, 256, 64, 64]}
    )
    with pytest.raises(
        ModelError,
        match=r"e3.onnx: SAM image encoder: expected input image\[1,3,S,S\] float32; got image\[1024,1024,3\]",
    ):
        SamOnnxBackend(encoder_path=hwc, decoder_path=models["decoder"])
    with pytest.raises(
        ModelError, match=r"decoder_512.onnx: SAM mask decoder: input image_embeddings\[1,256,32,32\] does not match"
    ):
        SamOnnxBackend(encoder_path=models["encoder"], decoder_path=models["decoder_512"])


def test_options_reject_unknown_and_bad_values(models):
    with pytest.raises(ConfigError, match=r"unknown option 'points_per_sid' \(did you mean 'points_per_side'\?\)"):
        SamOnnxOptions.from_mapping({"encoder_path": "e", "decoder_path": "d", "points_per_sid": 4})
    with pytest.raises(ConfigError, match="decoder_path is required"):
        SamOnnxOptions.from_mapping({"encoder_path": "e"})
    with pytest.raises(ConfigError, match=r"points_per_side=0"):
        SamOnnxOptions.from_mapping({"encoder_path": "e", "decoder_path": "d", "points_per_side": 0})
    with pytest.raises(ConfigError, match=r"option 'crop_to_roi' = 'yes' is not a bool"):
        SamOnnxOptions.from_mapping({"encoder_path": "e", "decoder_path": "d", "crop_to_roi": "yes"})
    o = SamOnnxOptions.from_mapping(
        {"encoder_path": "e", "decoder_path": "d", "pixel_mean": [0, 0, 0], "input_size": 512}
    )
    assert o.pixel_mean == (0.0, 0.0, 0.0) and o.input_size == 512 and o.encoder_path.name == "e"


# -- helpers -------------------------------------------------------------------------------


def test_stability_score_and_small_region_cleanup():
    logits = np.full((1, 10, 10), -5.0)
    logits[0, 2:6, 2:6] = 5.0
    logits[0, 6, 2:6] = 0.5  # a row that flips between thresholds +-1
    np.testing.assert_allclose(stability_score(logits, 0.0, 1.0), [16 / 20])
    m = np.zeros((40, 40), bool)
    m[5:30, 5:30] = True
    m[10, 10] = False  # a one-pixel hole
    m[35:37, 35:37] = True  # a speck
    clean = remove_small_regions(m, 10)
    assert clean[10, 10] and not clean[35:37, 35:37].any() and clean[5:30, 5:30].all()


def test_interior_points_are_deep_and_spread():
    m = np.zeros((60, 120), bool)
    m[10:50, 5:45] = True
    m[20:40, 70:110] = True
    pts = interior_points(m, 2)
    assert len(pts) == 2
    assert {int(pts[0, 0] < 60), int(pts[1, 0] < 60)} == {0, 1}  # one in each part
    assert all(m[int(y), int(x)] for x, y in pts)
