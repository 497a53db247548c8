"""The masking-backend protocol (paper section IV-A) and the registry that picks backends by name.

A backend turns one sensor image into object masks:

- ``proposals(image, context)`` -> list of (H, W) bool candidate masks, the zero-shot mode
  of Algorithm 1; the selection (``masking.selection``) picks among them by IoU with
  rendered masks, so a backend may return extraneous or partial candidates;
- ``prompt(image, prompt, context)`` -> one (H, W) bool mask, only for promptable backends:
  the low-uncertainty mode, prompted by the mask rendered at the estimate or by query
  points on it (``prompt`` is an (H, W) bool mask or an (N, 2) float array of pixel
  ``(x, y)``; ``split_prompt`` tells them apart).

What a backend may need besides the image travels in a :class:`MaskContext`.

Backends register under a name with ``@register_backend("name")`` and a config picks
them with ``get_backend(name, **options)``. The factory (usually the class) receives the
config's options as keyword arguments and raises :class:`~mvtop_cli.errors.ConfigError`
for an unknown or out-of-range option. Built-in backends are listed in
``_BUILTIN_BACKENDS`` as ``"module:attribute"`` and imported only when first asked for,
so that a backend's heavy dependencies (numba, ONNX Runtime) load only when it is used
and this module imports no backend.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from mvtop_cli.errors import ConfigError

# Built-in backends: name -> "module:attribute" of the factory, imported on first use
# (add yours here).
_BUILTIN_BACKENDS: dict[str, str] = {
    "difference": "mvtop_cli.masking.tactile:TactileDifferenceBackend",
    "classical": "mvtop_cli.masking.classical:ClassicalCameraBackend",
    "sam_onnx": "mvtop_cli.masking.onnx_sam:SamOnnxBackend",
    "instance_onnx": "mvtop_cli.masking.onnx_instance:InstanceOnnxBackend",
    "topic": "mvtop_cli.masking.recorded:RecordedMaskBackend",
}


@dataclass(frozen=True)
class MaskContext:
    """Inputs a backend may use besides the image; every field is optional.

    roi_box : (x0, y0, x1, y1) int or None
        Search window in pixels (half-open columns and rows); None = whole image.
    background : (H, W, 3) uint8 or None
        A tactile sensor's no-contact reference frame (RGB, same size as the image).
    indentation_m : (H, W) float or None
        A tactile sensor's gel indentation [m] from its depth topic, 0 = undeformed.
    extras : mapping
        Backend-specific inputs (e.g. camera intrinsics), by name; ``recorded_mask`` is
        the (H, W) label image an external segmenter recorded for the image (``topic``).
    """

    roi_box: tuple[int, int, int, int] | None = None
    background: np.ndarray | None = None
    indentation_m: np.ndarray | None = None
    extras: Mapping[str, Any] = field(default_factory=dict)


@runtime_checkable
class MaskBackend(Protocol):
    """Zero-shot backend: candidate masks for one image."""

    def proposals(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """Candidate masks, each (H, W) bool, for ``image`` (H, W, 3) uint8 RGB; [] if none."""
        ...


@runtime_checkable
class PromptableMaskBackend(MaskBackend, Protocol):
    """Backend that can also return one mask for a prompt (mask or query points)."""

    def prompt(self, image: np.ndarray, prompt: np.ndarray, context: MaskContext | None = None) -> np.ndarray:
        """The (H, W) bool mask of the object the prompt points at (all False if none)."""
        ...


BackendFactory = Callable[..., MaskBackend]

_BACKENDS: dict[str, BackendFactory] = {}


def register_backend(name: str) -> Callable[[BackendFactory], BackendFactory]:
    """Decorator registering a backend class (or factory) under ``name``."""

    def add(factory: BackendFactory) -> BackendFactory:
        path = f"{getattr(factory, '__module__', '')}:{getattr(factory, '__qualname__', '')}"
        taken = name in _BACKENDS and _BACKENDS[name] is not factory
        if taken or _BUILTIN_BACKENDS.get(name, path) != path:
            raise ValueError(f"masking backend {name!r} is already registered")
        _BACKENDS[name] = factory
        return factory

    return add


def available_backends() -> tuple[str, ...]:
    """Names ``get_backend`` accepts (registered and built-in), sorted."""
    return tuple(sorted({*_BACKENDS, *_BUILTIN_BACKENDS}))


def get_backend(name: str, **options: Any) -> MaskBackend:
    """A new backend ``name`` built with ``options`` (a config's ``masking.<sensor>.options``).

    Raises ConfigError for an unknown name, with the closest registered name as suggestion;
    the backend itself raises ConfigError for unknown or invalid options.
    """
    if not isinstance(name, str) or name not in available_backends():
        close = difflib.get_close_matches(str(name), available_backends(), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        known = ", ".join(available_backends())
        raise ConfigError(f"unknown masking backend {name!r}{hint}; expected one of: {known}")
    if name not in _BACKENDS:
        module, attribute = _BUILTIN_BACKENDS[name].split(":")
        _BACKENDS[name] = getattr(importlib.import_module(module), attribute)
    return _BACKENDS[name](**options)


def split_prompt(prompt: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(mask, None)`` for an (H, W) mask prompt, ``(None, points)`` for (N, 2) pixel (x, y).

    Parameters
    ----------
    prompt : (H, W) bool-like or (N, 2) float
    shape : (H, W) of the image

    Returns
    -------
    mask : (H, W) bool or None
    points : (N, 2) float64 or None
    """
    arr = np.asarray(prompt)
    if arr.shape == tuple(shape):
        return arr.astype(bool), None
    if arr.ndim == 2 and arr.shape[1] == 2:
        return None, arr.astype(np.float64)
    raise ValueError(f"prompt must be an {tuple(shape)} mask or (N, 2) pixel points, got shape {arr.shape}")


def roi_window(roi_box: Any, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Search window ``(x0, y0, x1, y1)`` (half-open columns and rows) clipped to an
    ``(H, W)`` image. ``roi_box`` is None (whole image), a 4-sequence ``(x0, y0, x1, y1)``,
    an object with ``x0, y0, width, height`` (a :class:`mvtop_cli.render.roi.Roi`), or a
    :class:`MaskContext` (its ``roi_box``). Raises ValueError below 2 x 2 pixels."""
    H, W = shape
    if isinstance(roi_box, MaskContext):
        roi_box = roi_box.roi_box
    if roi_box is None:
        return 0, 0, W, H
    if all(hasattr(roi_box, a) for a in ("x0", "y0", "width", "height")):
        x0, y0 = int(roi_box.x0), int(roi_box.y0)
        x1, y1 = x0 + int(roi_box.width), y0 + int(roi_box.height)
    else:
        x0, y0, x1, y1 = (int(round(float(v))) for v in roi_box)
    x0, x1 = max(0, min(x0, W)), max(0, min(x1, W))
    y0, y1 = max(0, min(y0, H)), max(0, min(y1, H))
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError(f"roi_box {roi_box!r} leaves less than 2x2 pixels of the {W}x{H} image")
    return x0, y0, x1, y1
