"""Shared pieces of the ONNX Runtime masking backends: sessions, signatures, options, mask utilities.

Loading a model is the boundary where ONNX Runtime's exceptions become one-line
:class:`~mvtop_cli.errors.ModelError` messages naming the file and what was expected.
Nothing here downloads anything: a model path that does not exist is an error.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import types
import typing
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from mvtop_cli.errors import ConfigError, ModelError

T = TypeVar("T")

# -- options ---------------------------------------------------------------------------


def _convert(key: str, value: Any, hint: Any, backend: str) -> Any:
    """``value`` converted to the field type ``hint`` (int, float, bool, str, Path, tuples
    and ``X | None`` of those); ConfigError naming ``key`` when it does not fit."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(key, value, inner, backend)
    try:
        if origin is tuple:
            if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
                raise TypeError("not a list")
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(_convert(key, v, args[0], backend) for v in value)
            if len(value) != len(args):
                raise ValueError(f"expected {len(args)} values, got {len(value)}")
            return tuple(_convert(key, v, a, backend) for v, a in zip(value, args))
        if hint is bool:
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError("not true/false")
            return bool(value)
        if hint is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError("not a whole number")
            return int(value)
        if hint is float:
            if isinstance(value, bool):
                raise TypeError("not a number")
            return float(value)
        if hint is str:
            if not isinstance(value, str):
                raise TypeError("not a string")
            return value
        if hint is Path:
            if not isinstance(value, (str, Path)):
                raise TypeError("not a path")
            return Path(value)
    except (TypeError, ValueError) as err:
        name = getattr(hint, "__name__", str(hint))
        raise ConfigError(f"{backend} masking backend: option {key!r} = {value!r} is not a {name} ({err})") from err
    raise TypeError(f"unsupported option type {hint!r} for {key!r}")  # a bug in an options class


def options_from_mapping(cls: type[T], options: Mapping[str, Any], backend: str) -> T:
    """An options dataclass ``cls`` from a config mapping (``masking.<sensor>.options``).

    Unknown keys raise ConfigError with the closest field name as a suggestion; values are
    converted to each field's annotated type (lists become tuples, strings paths).
    """
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    values: dict[str, Any] = {}
    for key, value in options.items():
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"{backend} masking backend: unknown option {key!r}{hint}")
        values[key] = _convert(key, value, hints[key], backend)
    return cls(**values)


def check_ranges(backend: str, obj: Any, checks: Mapping[str, bool]) -> None:
    """ConfigError listing the options of ``obj`` whose check in ``checks`` is False."""
    bad = [name for name, ok in checks.items() if not ok]
    if bad:
        values = ", ".join(f"{n}={getattr(obj, n)!r}" for n in bad)
        raise ConfigError(f"{backend} masking backend: option out of range: {values}")


# -- sessions and signatures -----------------------------------------------------------


@dataclass(frozen=True)
class TensorSpec:
    """Name, element type (e.g. ``'tensor(float)'``) and shape of a model input or output;
    a dimension is an int when fixed, a str or None when dynamic."""

    name: str
    type: str
    shape: tuple[int | str | None, ...]

    def fixed(self, axis: int) -> int | None:
        """The size of ``axis`` when the model fixes it, else None."""
        d = self.shape[axis]
        return d if isinstance(d, int) and d > 0 else None

    def __str__(self) -> str:
        dims = ",".join(str(d) if isinstance(d, int) else "?" for d in self.shape)
        return f"{self.name}[{dims}]"


def _specs(args) -> list[TensorSpec]:
    return [TensorSpec(a.name, a.type, tuple(a.shape)) for a in args]


def describe(specs: Sequence[TensorSpec]) -> str:
    """``'a[1,3,?,?], b[?]'``, for messages."""
    return ", ".join(str(s) for s in specs) or "none"


class OnnxModel:
    """An ONNX Runtime session on one model file, with its signature and wrapped errors.

    path : the .onnx file; role : what it is for messages (e.g. ``'SAM image encoder'``)
    num_threads : intra-op threads (0 = ONNX Runtime's default, one per core)
    providers : execution providers in order of preference
    """

    def __init__(
        self,
        path: Path | str,
        role: str,
        num_threads: int = 0,
        providers: Sequence[str] = ("CPUExecutionProvider",),
    ):
        self.path = Path(path)
        self.role = role
        if not self.path.is_file():
            what = "is a directory" if self.path.is_dir() else "not found"
            raise ModelError(f"{self.path}: {role} {what} (expected an .onnx file; nothing is downloaded)")
        try:
            import onnxruntime as ort
        except ImportError as err:  # pragma: no cover - onnxruntime is a dependency
            raise ModelError(f"{self.path}: onnxruntime is not installed (pip install onnxruntime)") from err
        so = ort.SessionOptions()
        so.intra_op_num_threads = int(num_threads)
        so.inter_op_num_threads = 1
        # Busy-waiting worker threads steal a shared machine's cores between runs.
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=so, providers=list(providers))
        except Exception as err:  # onnxruntime's pybind errors derive from Exception only
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ModelError(f"{self.path}: cannot load {role} as an ONNX model ({first})") from err
        self.inputs = _specs(self.session.get_inputs())
        self.outputs = _specs(self.session.get_outputs())

    def input(self, name: str) -> TensorSpec:
        return next(s for s in self.inputs if s.name == name)

    def output(self, name: str) -> TensorSpec:
        return next(s for s in self.outputs if s.name == name)

    def fail(self, message: str) -> ModelError:
        """A ModelError ``'<path>: <role>: <message>'``."""
        return ModelError(f"{self.path}: {self.role}: {message}")

    def require_inputs(self, names: Sequence[str], ranks: Mapping[str, int]) -> None:
        """ModelError unless the inputs are exactly ``names`` with the given ranks."""
        got = {s.name for s in self.inputs}
        if got != set(names):
            raise self.fail(f"expected inputs {', '.join(names)}; got {describe(self.inputs)}")
        for name, rank in ranks.items():
            spec = self.input(name)
            if len(spec.shape) != rank:
                raise self.fail(f"input {spec} has rank {len(spec.shape)}, expected rank {rank}")

    def require_outputs(self, names: Sequence[str], ranks: Mapping[str, int]) -> None:
        """ModelError unless every one of ``names`` is an output, with the given ranks."""
        got = {s.name for s in self.outputs}
        if not set(names) <= got:
            raise self.fail(f"expected outputs {', '.join(names)}; got {describe(self.outputs)}")
        for name, rank in ranks.items():
            spec = self.output(name)
            if len(spec.shape) != rank:
                raise self.fail(f"output {spec} has rank {len(spec.shape)}, expected rank {rank}")

    def run(self, outputs: Sequence[str] | None, feeds: Mapping[str, np.ndarray]) -> list[np.ndarray]:
        """Outputs for ``feeds``; an inference failure (e.g. a shape the model rejects) is a ModelError."""
        try:
            return self.session.run(None if outputs is None else list(outputs), dict(feeds))
        except Exception as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            shapes = ", ".join(f"{k}{list(np.shape(v))}" for k, v in feeds.items())
            raise self.fail(f"inference failed on inputs {shapes} ({first})") from err


# -- images, frames, caches -------------------------------------------------------------


def check_image(image: np.ndarray) -> np.ndarray:
    """``image`` as an (H, W, 3) uint8 array; ValueError otherwise."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    return image


def image_key(image: np.ndarray, *extra: Any) -> tuple:
    """Cache key of an image's content (BLAKE2 digest of its bytes, shape) and ``extra``."""
    digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16).digest()
    return (digest, image.shape, image.dtype.str, *extra)


class LruCache:
    """A small least-recently-used cache (embeddings, detections) keyed by image content."""

    def __init__(self, size: int):
        self.size = int(size)
        self._items: OrderedDict = OrderedDict()

    def get(self, key: tuple, compute: Callable[[], T]) -> T:
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = compute()
        if self.size > 0:
            self._items[key] = value
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._items)


@dataclass(frozen=True)
class ResizeFrame:
    """The map between image pixels and a model input that holds the image resized by
    ``scale`` to ``(resized_h, resized_w)`` at its top-left corner, padded bottom and right
    to ``(input_h, input_w)``.

    Points follow SAM's convention (``ResizeLongestSide.apply_coords``): a pixel coordinate
    ``(x, y)`` maps to ``(x * resized_w / W, y * resized_h / H)``.
    """

    height: int
    width: int
    resized_h: int
    resized_w: int
    input_h: int
    input_w: int

    @staticmethod
    def fit(shape: tuple[int, int], input_hw: tuple[int, int]) -> "ResizeFrame":
        """The largest resize of an ``(H, W)`` image into ``input_hw`` keeping its aspect
        ratio; sizes are rounded as SAM rounds them (``floor(s * n + 0.5)``), so the long
        side of a square input is exactly filled."""
        H, W = int(shape[0]), int(shape[1])
        ih, iw = int(input_hw[0]), int(input_hw[1])
        s = min(ih / H, iw / W)
        rh = min(ih, max(1, int(np.floor(H * s + 0.5))))
        rw = min(iw, max(1, int(np.floor(W * s + 0.5))))
        return ResizeFrame(H, W, rh, rw, ih, iw)

    def to_input(self, points_xy: np.ndarray) -> np.ndarray:
        """(N, 2) image pixel (x, y) -> (N, 2) model-input (x, y)."""
        p = np.asarray(points_xy, np.float64).reshape(-1, 2)
        return p * np.array([self.resized_w / self.width, self.resized_h / self.height])

    def to_image(self, points_xy: np.ndarray) -> np.ndarray:
        """(N, 2) model-input (x, y) -> (N, 2) image pixel (x, y) (inverse of ``to_input``)."""
        p = np.asarray(points_xy, np.float64).reshape(-1, 2)
        return p * np.array([self.width / self.resized_w, self.height / self.resized_h])

    def resize(self, image: np.ndarray) -> np.ndarray:
        """``image`` (H, W, C) resized to (resized_h, resized_w, C): area averaging when
        shrinking (no aliasing), bilinear when enlarging."""
        if (self.resized_h, self.resized_w) == (self.height, self.width):
            return image
        shrink = self.resized_h * self.resized_w < self.height * self.width
        interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        return cv2.resize(image, (self.resized_w, self.resized_h), interpolation=interpolation)

    def unpad(self, plane: np.ndarray) -> np.ndarray:
        """A model-input-sized (input_h, input_w) float map -> (H, W) in image pixels
        (crop the resized part, bilinear resize back)."""
        crop = np.ascontiguousarray(plane[: self.resized_h, : self.resized_w], dtype=np.float32)
        if crop.shape == (self.height, self.width):
            return crop
        return cv2.resize(crop, (self.width, self.height), interpolation=cv2.INTER_LINEAR)


# -- mask utilities ---------------------------------------------------------------------


def stability_score(logits: np.ndarray, threshold: float, offset: float) -> np.ndarray:
    """SAM's stability score of mask logits (..., h, w): the IoU of the masks thresholded at
    ``threshold + offset`` and ``threshold - offset`` (the first lies inside the second);
    1 when both are empty."""
    hi = np.count_nonzero(logits > threshold + offset, axis=(-2, -1))
    lo = np.count_nonzero(logits > threshold - offset, axis=(-2, -1))
    return np.where(lo > 0, hi / np.maximum(lo, 1), 1.0)


def remove_small_regions(mask: np.ndarray, min_area_px: int) -> np.ndarray:
    """``mask`` (h, w) bool without connected islands smaller than ``min_area_px`` and with
    holes smaller than that filled (the clean-up of SAM's automatic mask generator).
    An island is kept if it is the mask's largest, so a small object survives."""
    if min_area_px <= 0 or not mask.any():
        return mask
    out = mask.copy()
    # Holes: background components smaller than the limit (as in SAM, also at the border).
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~out).astype(np.uint8), connectivity=8)
    small = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] < min_area_px]
    if small:
        out |= np.isin(labels, small)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
    if n > 2:
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep = [i + 1 for i, a in enumerate(areas) if a >= min_area_px or a == areas.max()]
        out = np.isin(labels, keep)
    return out


def paste(mask: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int]) -> np.ndarray:
    """A window mask (y1 - y0, x1 - x0) bool placed at ``box`` = (x0, y0, x1, y1) of an
    all-False (H, W) mask."""
    x0, y0, x1, y1 = box
    out = np.zeros(shape, bool)
    out[y0:y1, x0:x1] = mask
    return out
