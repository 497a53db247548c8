"""Per-frame time of the masking backends a config names, on a log's first frames."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..config import Config
from ..estimator.observation import Observer
from ..geometry import se3
from ..io.frames import FrameReader
from ..io.mcap_reader import McapLog
from ..pipelines.estimate import log_topics, sensor_topics


def masking_speed(log_path: Path, cfg: Config, frames: int = 5) -> dict[str, float]:
    """Per-frame masking time [ms] on the first ``frames`` frames of a log: camera proposals
    (in a 160 px window around the image centre of the object's ground truth or the image
    centre), camera prompt (GrabCut from a disc), tactile mask; medians over frames."""
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
