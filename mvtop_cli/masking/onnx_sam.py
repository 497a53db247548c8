"""Zero-shot SAM-family masking backend (SAM, MobileSAM) on ONNX Runtime (paper section IV-A).

Two ONNX files, as SAM's ONNX exports ship them (see docs/models.md):

* the image encoder: one input (1, 3, S, S) float32 (S = 1024 for SAM and MobileSAM), the
  RGB image resized so that its long side is S, normalised with the ImageNet mean and
  standard deviation (in 0-255 units), zero-padded bottom and right; one output (or the
  output named ``image_embeddings``) (1, C, s, s), C = 256, s = 64;
* the prompt/mask decoder of SAM's ``scripts/export_onnx_model.py``: inputs
  ``image_embeddings`` (1, C, s, s), ``point_coords`` (1, N, 2) float32 in the resized
  S-frame, ``point_labels`` (1, N) float32 (1 foreground, 0 background, 2 and 3 box
  corners, -1 padding), ``mask_input`` (1, 1, 4s, 4s), ``has_mask_input`` (1,),
  ``orig_im_size`` (2,) float32 ``[H, W]``; outputs ``masks`` (1, K, H, W) logits at the
  original size, ``iou_predictions`` (1, K) (and ``low_res_masks``, unused).

The input size S, the embedding shape and the mask-input size are read from the models
when they are fixed there. The embedding of an image is computed once and cached by the
image's content.

Zero-shot mode (:meth:`SamOnnxBackend.proposals`) is SAM's automatic mask generator: a
grid of single-point prompts over the search window, masks kept when the predicted IoU
and the stability score pass their thresholds, small islands and holes cleaned up, and
duplicates removed by non-maximum suppression on mask IoU. Promptable mode
(:meth:`SamOnnxBackend.prompt`) prompts with the bounding box of a mask (the CAD model
rendered at the estimate) and interior points at the maxima of its distance transform,
or with given points, and returns the mask of highest predicted IoU.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mvtop_cli.bitmasks import mask_nms
from mvtop_cli.errors import ConfigError
from mvtop_cli.masking.base import MaskContext, register_backend, roi_window, split_prompt
from mvtop_cli.masking.onnx_common import (
    LruCache,
    OnnxModel,
    ResizeFrame,
    check_image,
    check_ranges,
    image_key,
    options_from_mapping,
    paste,
    remove_small_regions,
    stability_score,
)

DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")
DECODER_OUTPUTS = ("masks", "iou_predictions")
EMBEDDING_OUTPUT = "image_embeddings"

# SAM's pixel normalisation (ImageNet statistics in 0-255 units), segment_anything/modeling/sam.py.
IMAGENET_MEAN_255 = (123.675, 116.28, 103.53)
IMAGENET_STD_255 = (58.395, 57.12, 57.375)

# Point labels of SAM's prompt encoder.
LABEL_PAD, LABEL_BG, LABEL_FG, LABEL_BOX_TL, LABEL_BOX_BR = -1.0, 0.0, 1.0, 2.0, 3.0


@dataclass(frozen=True)
class SamOnnxOptions:
    """Options of :class:`SamOnnxBackend` (``masking.<sensor>.options`` of backend ``sam_onnx``).

    Models
    ------
    encoder_path, decoder_path : the two .onnx files (required; relative paths are taken
        from the working directory)
    input_size : encoder input side S [px]; None reads it from the encoder (1024 if the
        model leaves it dynamic); a value that contradicts a fixed model size is an error
    pixel_mean, pixel_std : normalisation ``(rgb - mean) / std`` in 0-255 units (use
        (0, 0, 0) and (1, 1, 1) for an encoder that normalises inside)
    num_threads : ONNX Runtime intra-op threads (0: one per core)
    providers : ONNX Runtime execution providers, in order of preference
    cache_size : image embeddings kept (keyed by image content and window)
    crop_to_roi : encode only the search window ``context.roi_box`` (a small object gets
        more of the encoder's resolution); False encodes the whole image once and only
        places the prompts in the window

    Zero-shot proposals (SAM's automatic mask generator)
    ----------------------------------------------------
    points_per_side : the prompt grid is points_per_side^2 points over the window (one
        decoder run each)
    pred_iou_thresh : masks with a lower predicted IoU are dropped
    stability_score_thresh, stability_score_offset : masks whose stability score (IoU of
        the masks at logit thresholds +-offset) is lower are dropped
    mask_threshold : logit above which a pixel is in the mask
    nms_iou_thresh : of two masks overlapping more (mask IoU), the lower-scored is dropped
    min_region_area_px : islands and holes smaller than this are removed / filled
    min_mask_area_px : smallest proposal [px]
    max_area_fraction : largest proposal, as a fraction of the window
    max_proposals : at most this many proposals, best predicted IoU first

    Promptable mode
    ---------------
    prompt_use_box : prompt with the prompt mask's bounding box
    prompt_points : interior foreground points taken from the prompt mask (maxima of its
        distance transform, spread apart); 0 with the box alone
    """

    encoder_path: Path | None = None
    decoder_path: Path | None = None
    input_size: int | None = None
    pixel_mean: tuple[float, float, float] = IMAGENET_MEAN_255
    pixel_std: tuple[float, float, float] = IMAGENET_STD_255
    num_threads: int = 0
    providers: tuple[str, ...] = ("CPUExecutionProvider",)
    cache_size: int = 2
    crop_to_roi: bool = True
    points_per_side: int = 16
    pred_iou_thresh: float = 0.88
    stability_score_thresh: float = 0.95
    stability_score_offset: float = 1.0
    mask_threshold: float = 0.0
    nms_iou_thresh: float = 0.7
    min_region_area_px: int = 100
    min_mask_area_px: int = 100
    max_area_fraction: float = 0.9
    max_proposals: int = 30
    prompt_use_box: bool = True
    prompt_points: int = 3

    def __post_init__(self) -> None:
        if self.encoder_path is None or self.decoder_path is None:
            missing = [n for n in ("encoder_path", "decoder_path") if getattr(self, n) is None]
            raise ConfigError(f"sam_onnx masking backend: option {' and '.join(missing)} is required (an .onnx file)")
        check_ranges(
            "sam_onnx",
            self,
            {
                "input_size": self.input_size is None or 16 <= self.input_size <= 8192,
                "pixel_std": all(s > 0 for s in self.pixel_std),
                "num_threads": self.num_threads >= 0,
                "providers": len(self.providers) > 0,
                "cache_size": self.cache_size >= 0,
                "points_per_side": 1 <= self.points_per_side <= 128,
                "pred_iou_thresh": self.pred_iou_thresh <= 1,
                "stability_score_thresh": self.stability_score_thresh <= 1,
                "stability_score_offset": self.stability_score_offset >= 0,
                "nms_iou_thresh": 0 < self.nms_iou_thresh <= 1,
                "min_region_area_px": self.min_region_area_px >= 0,
                "min_mask_area_px": self.min_mask_area_px >= 1,
                "max_area_fraction": 0 < self.max_area_fraction <= 1,
                "max_proposals": self.max_proposals >= 1,
                "prompt_points": 0 <= self.prompt_points <= 32,
            },
        )
        if not self.prompt_use_box and self.prompt_points == 0:
            raise ConfigError("sam_onnx masking backend: prompt_use_box=false needs prompt_points >= 1")

    @staticmethod
    def from_mapping(options: Mapping[str, Any]) -> "SamOnnxOptions":
        """Options from a config mapping; unknown keys raise ConfigError with a suggestion."""
        return options_from_mapping(SamOnnxOptions, options, "sam_onnx")


def grid_points(n_per_side: int) -> np.ndarray:
    """(n^2, 2) float64 (x, y) in [0, 1]: cell centres of an n x n grid (SAM's point grid)."""
    c = (np.arange(n_per_side) + 0.5) / n_per_side
    xx, yy = np.meshgrid(c, c)
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def interior_points(mask: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` (x, y) pixel points (k, 2) float64 deep inside ``mask`` (h, w) bool.

    The first is the maximum of the distance transform (the centre of the largest inscribed
    disc); each next one is the maximum outside the discs around the points taken so far,
    so the points spread over the mask (several parts of a shape split by an occluder).
    Points closer than 1 px to the boundary are not taken.
    """
    if count <= 0 or not mask.any():
        return np.zeros((0, 2))
    dist = cv2.distanceTransform(np.pad(mask, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    free = dist.copy()
    points = []
    for _ in range(count):
        r, c = np.unravel_index(int(np.argmax(free)), free.shape)
        if free[r, c] < 1.0:
            break
        points.append((float(c), float(r)))
        cv2.circle(free, (int(c), int(r)), max(int(np.ceil(dist[r, c])), 1), 0.0, -1)
    return np.asarray(points, np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class _Window:
    """What the encoder saw: ``box`` (x0, y0, x1, y1) of the image, its ``frame`` (window
    pixels <-> encoder input), and the ``embedding``."""

    box: tuple[int, int, int, int]
    frame: ResizeFrame
    embedding: np.ndarray


@register_backend("sam_onnx")
class SamOnnxBackend:
    """SAM / MobileSAM encoder + decoder on ONNX Runtime, registered as ``'sam_onnx'``.

    ``proposals(image, context)`` gives zero-shot candidates (automatic mask generation in
    ``context.roi_box``); ``prompt(image, prompt, context)`` one mask for a prompt mask or
    prompt points. The models are loaded and their signatures checked at construction
    (ModelError naming the file otherwise).
    """

    name = "sam_onnx"

    def __init__(self, options: SamOnnxOptions | None = None, **overrides: Any):
        """``options``, or keyword overrides of :class:`SamOnnxOptions` fields as a config
        file gives them (``get_backend('sam_onnx', encoder_path=..., decoder_path=...)``)."""
        if options is None:
            options = SamOnnxOptions.from_mapping(overrides)
        elif overrides:
            options = SamOnnxOptions.from_mapping({**dataclasses.asdict(options), **overrides})
        self.options = o = options
        self.encoder = OnnxModel(o.encoder_path, "SAM image encoder", o.num_threads, o.providers)
        self.decoder = OnnxModel(o.decoder_path, "SAM mask decoder", o.num_threads, o.providers)
        self._check_encoder()
        self._check_decoder()
        self._embeddings = LruCache(o.cache_size)

    # -- signatures ------------------------------------------------------------------------

    def _check_encoder(self) -> None:
        enc = self.encoder
        if len(enc.inputs) != 1:
            got = ", ".join(map(str, enc.inputs))
            raise enc.fail(f"expected one input image[1,3,S,S]; got {len(enc.inputs)}: {got}")
        spec = enc.inputs[0]
        if len(spec.shape) != 4 or spec.fixed(1) not in (None, 3) or spec.fixed(0) not in (None, 1):
            raise enc.fail(f"expected input image[1,3,S,S] float32; got {spec}")
        if spec.type != "tensor(float)":
            raise enc.fail(f"expected input {spec.name} of float32; got {spec.type}")
        h, w = spec.fixed(2), spec.fixed(3)
        if h is not None and w is not None and h != w:
            raise enc.fail(f"expected a square input image[1,3,S,S]; got {spec}")
        fixed = h or w
        wanted = self.options.input_size
        if fixed is not None and wanted is not None and wanted != fixed:
            raise enc.fail(f"input {spec} is fixed at {fixed} px but option input_size is {wanted}")
        self.input_name = spec.name
        self.input_size = int(fixed or wanted or 1024)
        outs = [s for s in enc.outputs if s.name == EMBEDDING_OUTPUT] or (enc.outputs if len(enc.outputs) == 1 else [])
        if not outs or len(outs[0].shape) != 4:
            raise enc.fail(f"expected output {EMBEDDING_OUTPUT}[1,C,s,s]; got {', '.join(map(str, enc.outputs))}")
        self.embedding_name = outs[0].name
        self._embedding_spec = outs[0]

    def _check_decoder(self) -> None:
        dec = self.decoder
        dec.require_inputs(DECODER_INPUTS, dict(zip(DECODER_INPUTS, (4, 3, 2, 4, 1, 1))))
        dec.require_outputs(DECODER_OUTPUTS, {"masks": 4, "iou_predictions": 2})
        emb_in, emb_out = dec.input("image_embeddings"), self._embedding_spec
        for axis in (1, 2, 3):
            a, b = emb_in.fixed(axis), emb_out.fixed(axis)
            if a is not None and b is not None and a != b:
                raise dec.fail(f"input {emb_in} does not match the encoder's output {emb_out} ({self.encoder.path})")
        mask_in = dec.input("mask_input")
        side = mask_in.fixed(2) or mask_in.fixed(3)
        emb_side = emb_in.fixed(2) or emb_out.fixed(2)
        self.mask_input_size = int(side or (4 * emb_side if emb_side else self.input_size // 4))

    # -- embedding -------------------------------------------------------------------------

    def preprocess(self, image: np.ndarray) -> tuple[np.ndarray, ResizeFrame]:
        """Encoder input (1, 3, S, S) float32 of an (h, w, 3) uint8 RGB image, and its frame."""
        S = self.input_size
        frame = ResizeFrame.fit(image.shape[:2], (S, S))
        small = frame.resize(image).astype(np.float32)
        mean, std = np.asarray(self.options.pixel_mean, np.float32), np.asarray(self.options.pixel_std, np.float32)
        small = (small - mean) / std
        x = np.zeros((1, 3, S, S), np.float32)
        x[0, :, : frame.resized_h, : frame.resized_w] = small.transpose(2, 0, 1)
        return x, frame

    def _window(self, image: np.ndarray, context: MaskContext | None) -> tuple[_Window, tuple[int, int, int, int]]:
        """The encoded window for this call and the search box (x0, y0, x1, y1), in image
        pixels: the encoded window is the search box when ``crop_to_roi``, else the image."""
        image = check_image(image)
        H, W = image.shape[:2]
        box = roi_window(context.roi_box if context is not None else None, (H, W))
        enc_box = box if self.options.crop_to_roi else (0, 0, W, H)
        x0, y0, x1, y1 = enc_box

        def encode() -> _Window:
            x, frame = self.preprocess(np.ascontiguousarray(image[y0:y1, x0:x1]))
            (emb,) = self.encoder.run([self.embedding_name], {self.input_name: x})
            return _Window(enc_box, frame, emb.astype(np.float32, copy=False))

        return self._embeddings.get(image_key(image, enc_box), encode), box

    def embedding(self, image: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """The encoder's (1, C, s, s) embedding of the window of ``image`` (cached)."""
        return self._window(image, context)[0].embedding

    # -- decoding --------------------------------------------------------------------------

    def decode(self, window: _Window, points_xy: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mask logits (K, h, w) float32 over the window and predicted IoUs (K,) for one prompt.

        points_xy : (N, 2) window pixel (x, y); labels : (N,) SAM point labels. Without box
        corners a padding point is appended, as SAM's ONNX example does.
        """
        f = window.frame
        coords = f.to_input(points_xy)
        labels = np.asarray(labels, np.float32).reshape(-1)
        if not np.any(labels >= LABEL_BOX_TL):
            coords = np.concatenate([coords, np.zeros((1, 2))])
            labels = np.concatenate([labels, [LABEL_PAD]]).astype(np.float32)
        m = self.mask_input_size
        feeds = {
            "image_embeddings": window.embedding,
            "point_coords": coords[None].astype(np.float32),
            "point_labels": labels[None].astype(np.float32),
            "mask_input": np.zeros((1, 1, m, m), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([f.height, f.width], np.float32),
        }
        masks, iou = self.decoder.run(DECODER_OUTPUTS, feeds)
        if masks.ndim != 4 or masks.shape[2:] != (f.height, f.width) or iou.shape[-1] != masks.shape[1]:
            raise self.decoder.fail(
                f"output masks{list(masks.shape)} / iou_predictions{list(iou.shape)} do not match "
                f"orig_im_size [{f.height}, {f.width}] (expected masks[1,K,{f.height},{f.width}], iou_predictions[1,K])"
            )
        return masks[0], iou.reshape(-1).astype(np.float64)

    # -- zero-shot proposals ---------------------------------------------------------------

    def proposals(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """Zero-shot candidate masks in the search window ``context.roi_box`` of ``image``.

        image : (H, W, 3) uint8 RGB
        Returns at most ``max_proposals`` (H, W) bool masks inside the window, best
        predicted IoU first, no two overlapping with mask IoU above ``nms_iou_thresh``.
        """
        o = self.options
        window, box = self._window(image, context)
        H, W = np.asarray(image).shape[:2]
        wx0, wy0, wx1, wy1 = window.box
        bx0, by0, bx1, by1 = box
        # Grid over the search box, in window pixels (window = box when cropping).
        grid = grid_points(o.points_per_side) * [bx1 - bx0, by1 - by0] + [bx0 - wx0, by0 - wy0]
        inside = np.zeros((wy1 - wy0, wx1 - wx0), bool)
        inside[by0 - wy0 : by1 - wy0, bx0 - wx0 : bx1 - wx0] = True
        max_area = o.max_area_fraction * (bx1 - bx0) * (by1 - by0)
        masks: list[np.ndarray] = []
        scores: list[float] = []
        for point in grid:
            logits, iou = self.decode(window, point[None], np.array([LABEL_FG]))
            stable = stability_score(logits, o.mask_threshold, o.stability_score_offset)
            for k in np.flatnonzero((iou >= o.pred_iou_thresh) & (stable >= o.stability_score_thresh)):
                mask = remove_small_regions((logits[k] > o.mask_threshold) & inside, o.min_region_area_px)
                if o.min_mask_area_px <= np.count_nonzero(mask) <= max_area:
                    masks.append(mask)
                    scores.append(float(iou[k]))
        if not masks:
            return []
        keep = mask_nms(np.stack(masks), np.asarray(scores), o.nms_iou_thresh)[: o.max_proposals]
        return [paste(masks[i], window.box, (H, W)) for i in keep]

    # -- promptable mode -------------------------------------------------------------------

    def prompt(self, image: np.ndarray, prompt: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """The (H, W) bool mask of the object a prompt points at.

        prompt : (H, W) bool mask (the CAD model rendered at the current estimate): prompted
            with its bounding box and ``prompt_points`` interior points; or (N, 2) pixel
            (x, y) foreground points. An empty mask or no point in the window gives all False.
        The decoder's mask of highest predicted IoU is returned, limited to the window.
        """
        image = check_image(image)
        H, W = image.shape[:2]
        prompt_mask, points = split_prompt(prompt, (H, W))
        window, box = self._window(image, context)
        wx0, wy0, wx1, wy1 = window.box
        empty = np.zeros((H, W), bool)
        if prompt_mask is not None:
            local = prompt_mask[wy0:wy1, wx0:wx1]
            if not local.any():
                return empty
            pts = interior_points(local, self.options.prompt_points)
            labels = [LABEL_FG] * len(pts)
            if self.options.prompt_use_box or len(pts) == 0:
                rows, cols = np.nonzero(local)
                corners = np.array([[cols.min(), rows.min()], [cols.max(), rows.max()]], np.float64)
                pts = np.concatenate([pts, corners])
                labels += [LABEL_BOX_TL, LABEL_BOX_BR]
        else:
            pts = points - [wx0, wy0]
            ok = (pts[:, 0] >= 0) & (pts[:, 0] <= wx1 - wx0 - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= wy1 - wy0 - 1)
            pts = pts[ok]
            if len(pts) == 0:
                return empty
            labels = [LABEL_FG] * len(pts)
        logits, iou = self.decode(window, pts, np.asarray(labels))
        best = int(np.argmax(iou))
        mask = logits[best] > self.options.mask_threshold
        out = paste(mask, window.box, (H, W))
        bx0, by0, bx1, by1 = box
        limited = np.zeros((H, W), bool)
        limited[by0:by1, bx0:bx1] = out[by0:by1, bx0:bx1]
        return limited
