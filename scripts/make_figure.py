"""Draw one frame of each sample log (both cameras, both tactile sensors) into docs/sim_frames.png.

Usage: python scripts/make_figure.py [--frame K]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.sim.objects import list_objects

REPO = Path(__file__).resolve().parents[1]
TILE = (320, 240)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    out[: h + 10, : w + 10] = (out[: h + 10, : w + 10] * 0.3).astype(np.uint8)
    cv2.putText(out, text, (5, h + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _zoom(img, T_world_object: np.ndarray) -> np.ndarray:
    """A 2x crop of a camera image centred on the object's origin."""
    p = (se3.invert(img.T_world_sensor) @ T_world_object)[:3, 3]
    u, v = img.camera.project(p)
    w, h = TILE[0] // 2, TILE[1] // 2
    x0 = int(np.clip(round(u) - w // 2, 0, img.image.shape[1] - w))
    y0 = int(np.clip(round(v) - h // 2 - 10, 0, img.image.shape[0] - h))
    return cv2.resize(img.image[y0 : y0 + h, x0 : x0 + w], TILE, interpolation=cv2.INTER_CUBIC)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame", type=int, default=22, help="frame index (a contact frame by default)")
    args = parser.parse_args(argv)
    rows = []
    for name in list_objects():
        cfg = load_config(REPO / "configs" / f"{name}.yaml")
        with McapLog(REPO / "sample_logs" / f"{name}.mcap") as log:
            frame = next(f for f in FrameReader(log, sensor_topics(cfg), log_topics(cfg)) if f.index == args.frame)
        tiles = []
        for sensor, img in frame.cameras.items():
            tiles.append(_label(_zoom(img, frame.T_world_object_gt), f"{name} | {sensor} camera, 2x crop"))
        for sensor, img in [*frame.cameras.items(), *frame.tactile.items()]:
            tile = cv2.resize(img.image, TILE, interpolation=cv2.INTER_AREA)
            kind = "camera" if sensor in frame.cameras else "tactile"
            tiles.append(_label(tile, f"{kind} {sensor}" + (" (in contact)" if frame.contact else "")))
        rows.append(np.hstack(tiles))
    out = REPO / "docs" / "sim_frames.png"
    cv2.imwrite(str(out), np.vstack(rows)[:, :, ::-1])
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
