"""Supervised instance-segmentation masking backend (Mask R-CNN style) on ONNX Runtime.

The paper's supervised baseline (section IV-A) is a Mask R-CNN trained on labelled views of
the object. This backend runs such a model exported to ONNX with torchvision's signature
(see docs/models.md):

* one input, the image as float32 ``(3, H, W)`` (torchvision's export) or ``(1, 3, H, W)``,
  RGB scaled by ``input_scale`` (1/255: values in [0, 1]) then ``(x - pixel_mean) /
  pixel_std`` (identity by default: torchvision normalises inside the model). When the
  model fixes H and W the image is resized keeping its aspect ratio and padded bottom and
  right with zeros (a letterbox anchored top-left); otherwise it goes in at its own size
  (or resized to ``input_size`` on its long side when that option is set);
* outputs ``boxes`` (N, 4) x0, y0, x1, y1 in input pixels, ``labels`` (N,) int,
  ``scores`` (N,) and ``masks`` (N, 1, h, w) probabilities: either over the whole input
  (torchvision pastes them, h, w = the input size) or per box (e.g. 28 x 28, pasted here
  into each box). Outputs with other names are taken in this order when there are four.

Proposals are the masks of instances of class ``class_id`` (any class when None) scoring
at least ``score_threshold``, best first, mapped back to image pixels and limited to the
search window ``context.roi_box``. ``prompt`` picks the proposal that best matches a
prompt mask (IoU) or holds the most prompt points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mvtop_cli.bitmasks import iou_matrix
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
)

OUTPUTS = ("boxes", "labels", "scores", "masks")
_RANKS = {"boxes": 2, "labels": 1, "scores": 1, "masks": 4}


@dataclass(frozen=True)
class InstanceOnnxOptions:
    """Options of :class:`InstanceOnnxBackend` (backend ``instance_onnx``).

    model_path : the .onnx file (required; relative to the working directory)
    class_id : label of the object's class (torchvision counts the background as 0, so a
        model trained on one object calls it 1); None accepts every class
    score_threshold : instances scoring less are dropped
    mask_threshold : mask probability above which a pixel is in the mask
    input_size : for a model with dynamic H, W: resize the image's long side to this
        (None feeds the image at its own size); ignored when the model fixes H, W
    input_scale, pixel_mean, pixel_std : model input = (rgb * input_scale - mean) / std,
        per channel, after ``channel_order``
    channel_order : 'rgb' (torchvision) or 'bgr' (e.g. detectron2)
    min_mask_area_px : smaller proposals (after the window) are dropped
    max_proposals : at most this many proposals, best score first
    num_threads, providers : ONNX Runtime intra-op threads (0: one per core) and providers
    cache_size : detections kept per image content
    """

    model_path: Path | None = None
    class_id: int | None = 1
    score_threshold: float = 0.5
    mask_threshold: float = 0.5
    input_size: int | None = None
    input_scale: float = 1.0 / 255.0
    pixel_mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pixel_std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    channel_order: str = "rgb"
    min_mask_area_px: int = 1
    max_proposals: int = 30
    num_threads: int = 0
    providers: tuple[str, ...] = ("CPUExecutionProvider",)
    cache_size: int = 2

    def __post_init__(self) -> None:
        if self.model_path is None:
            raise ConfigError("instance_onnx masking backend: option 'model_path' is required (an .onnx file)")
        check_ranges(
            "instance_onnx",
            self,
            {
                "class_id": self.class_id is None or self.class_id >= 0,
                "score_threshold": 0 <= self.score_threshold <= 1,
                "mask_threshold": 0 <= self.mask_threshold <= 1,
                "input_size": self.input_size is None or 16 <= self.input_size <= 8192,
                "input_scale": self.input_scale > 0,
                "pixel_std": all(s > 0 for s in self.pixel_std),
                "channel_order": self.channel_order in ("rgb", "bgr"),
                "min_mask_area_px": self.min_mask_area_px >= 1,
                "max_proposals": self.max_proposals >= 1,
                "num_threads": self.num_threads >= 0,
                "providers": len(self.providers) > 0,
                "cache_size": self.cache_size >= 0,
            },
        )

    @staticmethod
    def from_mapping(options: Mapping[str, Any]) -> "InstanceOnnxOptions":
        """Options from a config mapping; unknown keys raise ConfigError with a suggestion."""
        return options_from_mapping(InstanceOnnxOptions, options, "instance_onnx")


@dataclass(frozen=True)
class Detections:
    """Instances of one image, in image pixels, best score first.

    boxes : (N, 4) float64 x0, y0, x1, y1 [px]; labels : (N,) int64; scores : (N,) float64;
    masks : (N, H, W) bool
    """

    boxes: np.ndarray
    labels: np.ndarray
    scores: np.ndarray
    masks: np.ndarray


@register_backend("instance_onnx")
class InstanceOnnxBackend:
    """Mask R-CNN style instance segmentation on ONNX Runtime, registered as ``'instance_onnx'``.

    The model is loaded and its signature checked at construction (ModelError naming the
    file otherwise).
    """

    name = "instance_onnx"

    def __init__(self, options: InstanceOnnxOptions | None = None, **overrides: Any):
        if options is None:
            options = InstanceOnnxOptions.from_mapping(overrides)
        elif overrides:
            options = InstanceOnnxOptions.from_mapping({**dataclasses.asdict(options), **overrides})
        self.options = o = options
        self.model = OnnxModel(o.model_path, "instance segmentation model", o.num_threads, o.providers)
        self._check_model()
        self._detections = LruCache(o.cache_size)

    def _check_model(self) -> None:
        m = self.model
        if len(m.inputs) != 1:
            raise m.fail(f"expected one input image[3,H,W] or image[1,3,H,W]; got {', '.join(map(str, m.inputs))}")
        spec = m.inputs[0]
        rank = len(spec.shape)
        channels_last = rank in (3, 4) and spec.fixed(rank - 3) is None and spec.fixed(rank - 1) == 3
        if (
            rank not in (3, 4)
            or spec.fixed(rank - 3) not in (None, 3)
            or (rank == 4 and spec.fixed(0) not in (None, 1))
            or channels_last
        ):
            raise m.fail(f"expected input image[3,H,W] or image[1,3,H,W] float32; got {spec}")
        if spec.type != "tensor(float)":
            raise m.fail(f"expected input {spec.name} of float32; got {spec.type}")
        self.input_name, self.input_rank = spec.name, rank
        h, w = spec.fixed(rank - 2), spec.fixed(rank - 1)
        self.fixed_size = (h, w) if h is not None and w is not None else None
        names = [s.name for s in m.outputs]
        if set(OUTPUTS) <= set(names):
            self.output_names = OUTPUTS
        elif len(names) == 4:
            self.output_names = tuple(names)  # torchvision's order: boxes, labels, scores, masks
        else:
            raise m.fail(f"expected outputs {', '.join(OUTPUTS)}; got {', '.join(map(str, m.outputs))}")
        for role, name in zip(OUTPUTS, self.output_names):
            out = m.output(name)
            if len(out.shape) != _RANKS[role]:
                got = ", ".join(map(str, m.outputs))
                raise m.fail(f"expected outputs boxes[N,4], labels[N], scores[N], masks[N,1,h,w]; got {got}")

    # -- inference -------------------------------------------------------------------------

    def _frame(self, shape: tuple[int, int]) -> ResizeFrame:
        if self.fixed_size is not None:
            return ResizeFrame.fit(shape, self.fixed_size)
        if self.options.input_size is not None:
            s = self.options.input_size
            f = ResizeFrame.fit(shape, (s, s))
            return ResizeFrame(f.height, f.width, f.resized_h, f.resized_w, f.resized_h, f.resized_w)
        return ResizeFrame(shape[0], shape[1], shape[0], shape[1], shape[0], shape[1])

    def preprocess(self, image: np.ndarray) -> tuple[np.ndarray, ResizeFrame]:
        """Model input ((3, h, w) or (1, 3, h, w) float32) for an (H, W, 3) uint8 RGB image, and its frame."""
        o = self.options
        frame = self._frame(image.shape[:2])
        x = frame.resize(image).astype(np.float32)
        if o.channel_order == "bgr":
            x = x[..., ::-1]
        x = (x * np.float32(o.input_scale) - np.asarray(o.pixel_mean, np.float32)) / np.asarray(o.pixel_std, np.float32)
        chw = np.zeros((3, frame.input_h, frame.input_w), np.float32)
        chw[:, : frame.resized_h, : frame.resized_w] = x.transpose(2, 0, 1)
        return (chw[None] if self.input_rank == 4 else chw), frame

    def detect(self, image: np.ndarray) -> Detections:
        """All instances of ``image`` (H, W, 3) uint8 RGB above the score threshold and of the
        chosen class, in image pixels, best first (cached by image content)."""
        image = check_image(image)
        return self._detections.get(image_key(image), lambda: self._detect(image))

    def _detect(self, image: np.ndarray) -> Detections:
        o = self.options
        H, W = image.shape[:2]
        x, frame = self.preprocess(image)
        boxes, labels, scores, masks = self.model.run(self.output_names, {self.input_name: x})
        n = len(scores)
        if boxes.shape != (n, 4) or labels.shape[:1] != (n,) or masks.ndim != 4 or masks.shape[0] != n:
            raise self.model.fail(
                f"outputs boxes{list(boxes.shape)}, labels{list(labels.shape)}, scores{list(scores.shape)}, "
                f"masks{list(masks.shape)} disagree (expected boxes[N,4], labels[N], scores[N], masks[N,1,h,w])"
            )
        keep = np.asarray(scores, np.float64) >= o.score_threshold
        if o.class_id is not None:
            keep &= np.asarray(labels).astype(np.int64) == o.class_id
        idx = np.flatnonzero(keep)
        idx = idx[np.argsort(-np.asarray(scores, np.float64)[idx], kind="stable")]
        full = masks.shape[2:] == (frame.input_h, frame.input_w)
        scale = np.array([W / frame.resized_w, H / frame.resized_h] * 2)
        out_masks, out_boxes = [], []
        for i in idx:
            box_in = np.asarray(boxes[i], np.float64)
            plane = masks[i, 0].astype(np.float32) if full else self._paste_box(masks[i, 0], box_in, frame)
            out_masks.append(frame.unpad(plane) > o.mask_threshold)
            out_boxes.append(box_in * scale)
        return Detections(
            boxes=np.asarray(out_boxes, np.float64).reshape(-1, 4),
            labels=np.asarray(labels)[idx].astype(np.int64),
            scores=np.asarray(scores, np.float64)[idx],
            masks=np.asarray(out_masks, bool).reshape(-1, H, W),
        )

    @staticmethod
    def _paste_box(mask: np.ndarray, box: np.ndarray, frame: ResizeFrame) -> np.ndarray:
        """A per-box (h, w) probability map resized onto ``box`` (x0, y0, x1, y1, continuous
        input pixels) of an (input_h, input_w) zero plane."""
        plane = np.zeros((frame.input_h, frame.input_w), np.float32)
        x0, y0, x1, y1 = box
        # The pixels whose centres (c + 0.5, r + 0.5) lie in the box.
        c0, r0 = max(int(np.ceil(x0 - 0.5)), 0), max(int(np.ceil(y0 - 0.5)), 0)
        c1, r1 = min(int(np.floor(x1 - 0.5)) + 1, frame.input_w), min(int(np.floor(y1 - 0.5)) + 1, frame.input_h)
        if c1 <= c0 or r1 <= r0 or x1 <= x0 or y1 <= y0:
            return plane
        # Sample the box-relative map at their centres (its edge values reach the box edge).
        h, w = mask.shape
        cols = ((np.arange(c0, c1) + 0.5 - x0) / (x1 - x0) * w - 0.5).astype(np.float32)
        rows = ((np.arange(r0, r1) + 0.5 - y0) / (y1 - y0) * h - 0.5).astype(np.float32)
        map_x, map_y = np.meshgrid(cols, rows)
        plane[r0:r1, c0:c1] = cv2.remap(
            mask.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        return plane

    # -- backend protocol ------------------------------------------------------------------

    def proposals(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """The (H, W) bool masks of the chosen class above the score threshold, best first,
        limited to the search window ``context.roi_box``; [] if none."""
        det = self.detect(image)
        H, W = det.masks.shape[1:] if len(det.masks) else np.asarray(image).shape[:2]
        x0, y0, x1, y1 = roi_window(context.roi_box if context is not None else None, (H, W))
        out = []
        for mask in det.masks:
            limited = np.zeros((H, W), bool)
            limited[y0:y1, x0:x1] = mask[y0:y1, x0:x1]
            if np.count_nonzero(limited) >= self.options.min_mask_area_px:
                out.append(limited)
            if len(out) >= self.options.max_proposals:
                break
        return out

    def prompt(self, image: np.ndarray, prompt: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """The proposal best matching the prompt: highest IoU with a prompt mask (H, W), or
        most of the (N, 2) pixel (x, y) prompt points inside (ties: higher score); all
        False when none overlaps."""
        image = check_image(image)
        shape = image.shape[:2]
        prompt_mask, points = split_prompt(prompt, shape)
        props = self.proposals(image, context)
        if not props:
            return np.zeros(shape, bool)
        stack = np.stack(props)
        if prompt_mask is not None:
            match = iou_matrix(stack, prompt_mask[None], empty_score=0.0)[:, 0]
        else:
            cols, rows = np.rint(points[:, 0]).astype(int), np.rint(points[:, 1]).astype(int)
            ok = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
            match = stack[:, rows[ok], cols[ok]].sum(axis=1).astype(np.float64)
        best = int(np.argmax(match))  # proposals are best score first: ties keep the better
        return stack[best].copy() if match[best] > 0 else np.zeros(shape, bool)
