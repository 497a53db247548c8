"""Tiny ONNX models with the SAM encoder/decoder and Mask R-CNN signatures, built with onnx.helper.

They stand in for real weights: their outputs are known functions of the inputs, so the
backends' coordinate handling can be checked to the pixel.

Scenes: a dark background with a red disc (object A) and a green disc (object B).

* :func:`sam_encoder`: ``image`` (1, 3, S, S) -> ``image_embeddings`` (1, C, E, E) whose
  channels 0-5 hold, for A then B, the centroid x, y and the equal-area radius [input px]
  of the pixels that are red (resp. green) in the normalised input, and the other
  channels the channel-mean of the input average-pooled to E x E.
* :func:`sam_decoder`: maps the prompt points and the centroids back to original pixels
  (``x * W / round(W * S / max(H, W))``, SAM's resize) and returns, when a foreground point
  falls in disc A or B, the logits ``logit_scale * (r - distance)`` of the discs hit
  (iou 0.95); otherwise a disc of ``miss_radius`` px around the first foreground point
  (iou 0.2). With ``multimask``, a second mask is always that small disc (iou 0.5).
* :func:`instance_model`: ``image`` (3, H, W) or fixed (1, 3, h, w) in [0, 1] -> two
  instances: A (label 1, score 0.9) and B (label 2, score 0.6), masks ``clip(R - G)``
  and ``clip(G - R)`` over the whole input, constant boxes.
* :func:`box_mask_model`: fixed input, constant boxes with constant per-box 28 x 28 masks.
* :func:`signature_model`: any input/output names and shapes, constant outputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
FLOAT = TensorProto.FLOAT


class _Graph:
    """Collects nodes and constants; ``op`` returns the output name."""

    def __init__(self):
        self.nodes: list = []
        self.inits: list = []
        self._n = 0

    def name(self, base: str) -> str:
        self._n += 1
        return f"{base}_{self._n}"

    def const(self, value, dtype=np.float32) -> str:
        name = self.name("c")
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype), name))
        return name

    def op(self, op_type: str, *inputs: str, out: str | None = None, **attrs) -> str:
        out = out or self.name(op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attrs))
        return out

    def save(self, path: Path, inputs, outputs, name: str) -> Path:
        graph = helper.make_graph(self.nodes, name, inputs, outputs, self.inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
        model.ir_version = 8
        onnx.checker.check_model(model)
        onnx.save(model, str(path))
        return Path(path)


def _info(name: str, shape, elem=FLOAT):
    return helper.make_tensor_value_info(name, elem, list(shape))


# -- SAM ------------------------------------------------------------------------------------

# Mid-grey (127.5) after SAM's normalisation, per channel: the threshold between a
# channel's 0 and 255 (an edge pixel resized half in counts half in area).
_MID_R = (127.5 - 123.675) / 58.395
_MID_G = (127.5 - 116.28) / 57.12


def sam_encoder(
    path: Path, input_size: int = 1024, embed_side: int = 64, channels: int = 256, input_name: str = "image"
) -> Path:
    g = _Graph()
    S, E = input_size, embed_side
    img = input_name
    red = g.op("Slice", img, g.const([0], np.int64), g.const([1], np.int64), g.const([1], np.int64))
    green = g.op("Slice", img, g.const([1], np.int64), g.const([2], np.int64), g.const([1], np.int64))
    red_on, green_on = g.op("Greater", red, g.const(_MID_R)), g.op("Greater", green, g.const(_MID_G))
    in_a = g.op("Cast", g.op("And", red_on, g.op("Not", green_on)), to=FLOAT)  # (1,1,S,S)
    in_b = g.op("Cast", g.op("And", green_on, g.op("Not", red_on)), to=FLOAT)
    ramp = g.op("Range", g.const(0.0), g.const(float(S)), g.const(1.0))
    xs = g.op("Reshape", ramp, g.const([1, 1, 1, S], np.int64))
    ys = g.op("Reshape", ramp, g.const([1, 1, S, 1], np.int64))
    params = []
    for ind in (in_a, in_b):
        area = g.op("ReduceSum", ind, keepdims=1)  # (1,1,1,1)
        denom = g.op("Add", area, g.const(1e-6))
        cx = g.op("Div", g.op("ReduceSum", g.op("Mul", ind, xs), keepdims=1), denom)
        cy = g.op("Div", g.op("ReduceSum", g.op("Mul", ind, ys), keepdims=1), denom)
        r = g.op("Sqrt", g.op("Div", area, g.const(np.pi)))
        params += [cx, cy, r]
    p = g.op("Concat", *params, axis=1)  # (1,6,1,1)
    p = g.op("Expand", p, g.const([1, 6, E, E], np.int64))
    k = S // E
    pooled = g.op("AveragePool", img, kernel_shape=[k, k], strides=[k, k])
    pooled = g.op("ReduceMean", pooled, axes=[1], keepdims=1)  # opset 17: axes attribute
    pooled = g.op("Expand", pooled, g.const([1, channels - 6, E, E], np.int64))
    g.op("Concat", p, pooled, axis=1, out="image_embeddings")
    return g.save(path, [_info(img, [1, 3, S, S])], [_info("image_embeddings", [1, channels, E, E])], "sam_encoder")


def sam_decoder(
    path: Path,
    input_size: int = 1024,
    embed_side: int = 64,
    channels: int = 256,
    logit_scale: float = 10.0,
    miss_radius: float = 6.0,
    multimask: bool = False,
    rename: dict[str, str] | None = None,
) -> Path:
    rename = rename or {}
    n = {
        k: rename.get(k, k)
        for k in ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")
    }
    g = _Graph()
    S, E, M = float(input_size), embed_side, 4 * embed_side
    size = n["orig_im_size"]
    H = g.op("Gather", size, g.const(0, np.int64), axis=0)  # scalar
    W = g.op("Gather", size, g.const(1, np.int64), axis=0)
    s = g.op("Div", g.const(S), g.op("Max", H, W))
    half = g.const(0.5)
    new_h = g.op("Floor", g.op("Add", g.op("Mul", H, s), half))
    new_w = g.op("Floor", g.op("Add", g.op("Mul", W, s), half))
    sx, sy = g.op("Div", W, new_w), g.op("Div", H, new_h)
    sr = g.op("Sqrt", g.op("Mul", sx, sy))
    # Points -> original pixels, (1, N) each.
    coords = n["point_coords"]
    px = g.op("Mul", g.op("Squeeze", g.op("Slice", coords, g.const([0], np.int64), g.const([1], np.int64),
                                          g.const([2], np.int64)), g.const([2], np.int64)), sx)
    py = g.op("Mul", g.op("Squeeze", g.op("Slice", coords, g.const([1], np.int64), g.const([2], np.int64),
                                          g.const([2], np.int64)), g.const([2], np.int64)), sy)
    fg = g.op("Equal", n["point_labels"], g.const(1.0))  # (1, N)
    # Object parameters from the embedding.
    par = g.op("Slice", n["image_embeddings"], g.const([0, 0, 0], np.int64), g.const([6, 1, 1], np.int64),
               g.const([1, 2, 3], np.int64))
    par = g.op("Reshape", par, g.const([6], np.int64))
    P = [g.op("Gather", par, g.const(i, np.int64), axis=0) for i in range(6)]  # scalars
    # Pixel grid (1, 1, H, W).
    u = g.op("Unsqueeze", g.op("Range", g.const(0.0), W, g.const(1.0)), g.const([0, 1, 2], np.int64))
    v = g.op("Unsqueeze", g.op("Range", g.const(0.0), H, g.const(1.0)), g.const([0, 1, 3], np.int64))
    scale = g.const(logit_scale)

    def disc_logits(cx, cy, r):
        d = g.op("Sqrt", g.op("Add", g.op("Pow", g.op("Sub", u, cx), g.const(2.0)),
                              g.op("Pow", g.op("Sub", v, cy), g.const(2.0))))
        return g.op("Mul", scale, g.op("Sub", r, d))

    hits, objects = [], []
    for i in (0, 3):
        cx, cy, r = g.op("Mul", P[i], sx), g.op("Mul", P[i + 1], sy), g.op("Mul", P[i + 2], sr)
        d2 = g.op("Add", g.op("Pow", g.op("Sub", px, cx), g.const(2.0)), g.op("Pow", g.op("Sub", py, cy), g.const(2.0)))
        inside = g.op("And", g.op("LessOrEqual", d2, g.op("Mul", r, r)), fg)
        hit = g.op("ReduceMax", g.op("Cast", inside, to=FLOAT), keepdims=0)  # scalar
        hit_b = g.op("Greater", hit, g.const(0.5))
        hits.append(hit_b)
        objects.append(g.op("Where", hit_b, disc_logits(cx, cy, r), g.const(-100.0)))
    any_hit = g.op("Or", *hits)
    both = g.op("Max", *objects)
    # The first foreground point, as (1,1,1,1) x and y.
    first = g.op("ArgMax", g.op("Cast", fg, to=FLOAT), axis=1, keepdims=0)  # (1,)
    fx = g.op("Reshape", g.op("Gather", g.op("Reshape", px, g.const([-1], np.int64)), first, axis=0),
              g.const([1, 1, 1, 1], np.int64))
    fy = g.op("Reshape", g.op("Gather", g.op("Reshape", py, g.const([-1], np.int64)), first, axis=0),
              g.const([1, 1, 1, 1], np.int64))
    miss = disc_logits(fx, fy, g.const(miss_radius))
    main = g.op("Where", any_hit, both, miss)
    iou = g.op("Where", any_hit, g.const([[0.95]]), g.const([[0.2]]))  # (1, 1)
    low = g.op("Mul", n["mask_input"], g.const(0.0))
    K = 2 if multimask else 1
    if multimask:
        g.op("Concat", main, miss, axis=1, out="masks")
        g.op("Concat", iou, g.const([[0.5]]), axis=1, out="iou_predictions")
        g.op("Concat", low, low, axis=1, out="low_res_masks")
    else:
        g.op("Identity", main, out="masks")
        g.op("Identity", iou, out="iou_predictions")
        g.op("Identity", low, out="low_res_masks")
    inputs = [
        _info(n["image_embeddings"], [1, channels, E, E]),
        _info(n["point_coords"], [1, "num_points", 2]),
        _info(n["point_labels"], [1, "num_points"]),
        _info(n["mask_input"], [1, 1, M, M]),
        _info(n["has_mask_input"], [1]),
        _info(n["orig_im_size"], [2]),
    ]
    outputs = [
        _info("masks", [1, K, "H", "W"]),
        _info("iou_predictions", [1, K]),
        _info("low_res_masks", [1, K, M, M]),
    ]
    return g.save(path, inputs, outputs, "sam_decoder")


# -- instance segmentation ------------------------------------------------------------------


def instance_model(path: Path, fixed_hw: tuple[int, int] | None = None) -> Path:
    g = _Graph()
    if fixed_hw is None:
        x = g.op("Identity", "image")  # (3, H, W)
        in_shape = [3, "H", "W"]
    else:
        x = g.op("Squeeze", "image", g.const([0], np.int64))
        in_shape = [1, 3, *fixed_hw]
    red = g.op("Slice", x, g.const([0], np.int64), g.const([1], np.int64), g.const([0], np.int64))  # (1,H,W)
    green = g.op("Slice", x, g.const([1], np.int64), g.const([2], np.int64), g.const([0], np.int64))
    zero, one = g.const(0.0), g.const(1.0)
    a = g.op("Clip", g.op("Sub", red, green), zero, one)
    b = g.op("Clip", g.op("Sub", green, red), zero, one)
    g.op("Concat", g.op("Unsqueeze", a, g.const([0], np.int64)), g.op("Unsqueeze", b, g.const([0], np.int64)),
         axis=0, out="masks")
    g.op("Identity", g.const([[10, 10, 50, 50], [60, 60, 90, 90]]), out="boxes")
    g.op("Identity", g.const([1, 2], np.int64), out="labels")
    g.op("Identity", g.const([0.9, 0.6]), out="scores")
    outputs = [
        _info("boxes", ["N", 4]),
        _info("labels", ["N"], TensorProto.INT64),
        _info("scores", ["N"]),
        _info("masks", ["N", 1, "h", "w"]),
    ]
    return g.save(path, [_info("image", in_shape)], outputs, "instance")


def box_mask_model(path: Path, fixed_hw: tuple[int, int], boxes, labels, scores, mask_side: int = 28) -> Path:
    """Constant detections with per-box masks that fill each box (all ones)."""
    g = _Graph()
    n = len(scores)
    # Depend on the input so that the graph is not all constants.
    zero = g.op("Mul", g.op("ReduceMean", "image", keepdims=0), g.const(0.0))
    g.op("Add", g.const(boxes), zero, out="boxes")
    g.op("Identity", g.const(labels, np.int64), out="labels")
    g.op("Identity", g.const(scores), out="scores")
    g.op("Identity", g.const(np.ones((n, 1, mask_side, mask_side))), out="masks")
    outputs = [
        _info("boxes", [n, 4]),
        _info("labels", [n], TensorProto.INT64),
        _info("scores", [n]),
        _info("masks", [n, 1, mask_side, mask_side]),
    ]
    return g.save(path, [_info("image", [1, 3, *fixed_hw])], outputs, "box_masks")


def signature_model(path: Path, inputs: dict[str, list], outputs: dict[str, list]) -> Path:
    """A model with the given input and output names and shapes (float32); the outputs are
    zeros (dynamic dimensions of size 1) plus 0 x the mean of the first input."""
    g = _Graph()
    first = next(iter(inputs))
    zero = g.op("Mul", g.op("ReduceMean", first, keepdims=0), g.const(0.0))
    for name, shape in outputs.items():
        concrete = [d if isinstance(d, int) else 1 for d in shape]
        g.op("Add", g.const(np.zeros(concrete)), zero, out=name)
    return g.save(
        path,
        [_info(k, v) for k, v in inputs.items()],
        [_info(k, v) for k, v in outputs.items()],
        "signature",
    )
