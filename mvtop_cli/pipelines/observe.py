"""Observed object masks from a frame's images, with the masking backends the config names.

Cameras use ``masking.camera`` (``classical`` by default, or ``sam_onnx`` / ``instance_onnx``):
zero-shot proposals for Algorithm 1-2 and the promptable mode. Tactile sensors use the
indentation depth topic when the log has one (undeformed pixels removed before binarising),
else ``masking.tactile`` (``difference``: the change from a no-contact reference frame, given
as ``options.reference_image`` or taken as the first tactile image of the log).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..config import BackendConfig, Config
from ..errors import ConfigError
from ..masking.base import MaskContext, get_backend
from ..records import SensorImage

TACTILE_DEPTH_THRESHOLD_M = 2e-5  # indentation below this is the undeformed gel


def _resolve_paths(options: dict[str, Any], base: Path | None) -> dict[str, Any]:
    """Option values of keys ending in ``_path`` resolved against the config's folder."""
    out = dict(options)
    for key, value in options.items():
        if key.endswith("_path") and isinstance(value, str) and base is not None and not Path(value).is_absolute():
            out[key] = str((base / value).resolve())
    return out


def make_backend(spec: BackendConfig, cfg: Config, key: str, drop: tuple[str, ...] = ()):
    """The backend ``spec`` names, with its options (paths relative to the config file)."""
    base = cfg.source.resolve().parent if cfg.source is not None else None
    options = {k: v for k, v in _resolve_paths(spec.options, base).items() if k not in drop}
    try:
        return get_backend(spec.backend, **options)
    except ConfigError as err:
        where = f"{cfg.source}: " if cfg.source is not None else ""
        raise ConfigError(f"{where}{key}: {err}") from None


class Observer:
    """Makes the observed masks of one log's frames."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.camera = make_backend(cfg.masking.camera, cfg, "masking.camera")
        self._tactile_spec = cfg.masking.tactile
        self._tactile = None
        self._references: dict[str, np.ndarray] = {}
        ref = cfg.masking.tactile.options.get("reference_image")
        self._reference_file = None
        if ref is not None:
            base = cfg.source.resolve().parent if cfg.source is not None else Path.cwd()
            self._reference_file = (base / ref) if not Path(ref).is_absolute() else Path(ref)

    def camera_proposals(self, img: SensorImage, roi_box: tuple[int, int, int, int]) -> list[np.ndarray]:
        """Zero-shot proposals (full-image bool masks) inside ``roi_box``; none when the box
        leaves under 2 x 2 pixels of the image (a belief at the image edge: the other
        proposals and sensors carry the frame)."""
        H, W = img.image.shape[:2]
        if min(roi_box[2], W) - max(roi_box[0], 0) < 2 or min(roi_box[3], H) - max(roi_box[1], 0) < 2:
            return []
        return list(self.camera.proposals(img.image, MaskContext(roi_box=roi_box)))

    def camera_prompt(self, img: SensorImage, prompt_mask: np.ndarray) -> np.ndarray:
        """The object mask prompted by the CAD silhouette at the current estimate."""
        return np.asarray(self.camera.prompt(img.image, prompt_mask), dtype=bool)

    def tactile_mask(self, img: SensorImage) -> np.ndarray:
        """The contact region (full-image bool mask) of one tactile image."""
        if img.depth is not None:
            return np.asarray(img.depth) > TACTILE_DEPTH_THRESHOLD_M
        if self._tactile is None:
            self._tactile = make_backend(self._tactile_spec, self.cfg, "masking.tactile", drop=("reference_image",))
        ref = self._reference(img)
        return np.asarray(self._tactile.contact_mask(img.image, MaskContext(background=ref)), dtype=bool)

    def _reference(self, img: SensorImage) -> np.ndarray:
        if img.sensor not in self._references:
            if self._reference_file is not None:
                import cv2

                ref = cv2.imread(str(self._reference_file), cv2.IMREAD_COLOR)
                if ref is None:
                    raise ConfigError(f"{self._reference_file}: cannot read the tactile reference image "
                                      "(masking.tactile.options.reference_image)")
                ref = ref[:, :, ::-1]
            else:
                ref = img.image  # the first image of the sensor: the log starts before contact
            if ref.shape != img.image.shape:
                raise ConfigError(f"masking.tactile.options.reference_image: size {ref.shape[:2]} differs from "
                                  f"the {img.sensor!r} images {img.image.shape[:2]}")
            self._references[img.sensor] = np.ascontiguousarray(ref)
        return self._references[img.sensor]


def masking_speed(log_path: Path, cfg: Config, frames: int = 5) -> dict[str, float]:
    """Per-frame masking time [ms] on the first ``frames`` frames of a log: camera proposals
    (in a 160 px window around the image centre of the object's ground truth or the image
    centre), camera prompt (GrabCut from a disc), tactile mask; medians over frames."""
    import time

    from ..io.frames import FrameReader
    from ..io.mcap_reader import McapLog
    from .estimate import log_topics, sensor_topics

    observer = Observer(cfg)
    times: dict[str, list[float]] = {"camera_proposals_ms": [], "camera_prompt_ms": [], "tactile_ms": []}
    with McapLog(log_path) as log:
        for k, frame in enumerate(FrameReader(log, sensor_topics(cfg), log_topics(cfg))):
            if k >= frames:
                break
            cam_prop = cam_prompt = tac = 0.0
            for img in frame.cameras.values():
                H, W = img.image.shape[:2]
                cx, cy = W // 2, H // 2
                if frame.T_world_object_gt is not None:
                    from ..geometry import se3

                    p = (se3.invert(img.T_world_sensor) @ frame.T_world_object_gt)[:3, 3]
                    if p[2] > 0:
                        cx, cy = (int(np.clip(v, 80, lim - 80)) for v, lim in zip(img.camera.project(p), (W, H)))
                box = (cx - 80, cy - 80, cx + 80, cy + 80)
                t0 = time.perf_counter()
                observer.camera_proposals(img, box)
                t1 = time.perf_counter()
                yy, xx = np.mgrid[0:H, 0:W]
                observer.camera_prompt(img, (xx - cx) ** 2 + (yy - cy) ** 2 < 20**2)
                t2 = time.perf_counter()
                cam_prop, cam_prompt = cam_prop + (t1 - t0), cam_prompt + (t2 - t1)
            for img in frame.tactile.values():
                t0 = time.perf_counter()
                observer.tactile_mask(img)
                tac += time.perf_counter() - t0
            times["camera_proposals_ms"].append(1e3 * cam_prop)
            times["camera_prompt_ms"].append(1e3 * cam_prompt)
            times["tactile_ms"].append(1e3 * tac)
    return {k: float(np.median(v)) for k, v in times.items() if v}
