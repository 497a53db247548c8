"""Draw the front and side camera images of the default and the hard simulated scene (same
object, seed and frames) into docs/hard_scene.png, with the recorded object mask's outline.

Usage: python scripts/make_scene_figure.py [--object cube] [--seed 1] [--frames 0,9]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from mvtop_cli.io.frames import FrameReader, LogTopics, SensorTopics
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.simulate import SimulateOptions, scene_options, simulate
from mvtop_cli.sim.episode import EpisodeOptions

REPO = Path(__file__).resolve().parents[1]
TILE = (320, 240)


def _tile(img: np.ndarray, mask: np.ndarray, text: str) -> np.ndarray:
    out = cv2.resize(img, TILE, interpolation=cv2.INTER_AREA)
    small = cv2.resize((mask > 0).astype(np.uint8), TILE, interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(small, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (0, 255, 255), 1)
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
    out[: h + 10, : w + 10] = (out[: h + 10, : w + 10] * 0.3).astype(np.uint8)
    cv2.putText(out, text, (5, h + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--object", default="cube")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--frames", default="0,9")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "hard_scene.png")
    args = parser.parse_args()
    picks = [int(v) for v in args.frames.split(",")]
    n = max(picks) + 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in ("default", "hard"):
            log = Path(tmp) / f"{scene}.mcap"
            base = SimulateOptions(episode=EpisodeOptions(frames=max(n, 4)), mask_topics=True)
            simulate(args.object, args.seed, log, scene_options(base, scene))
            sensors = [SensorTopics(c, "camera", f"/cameras/{c}/image/compressed", f"/cameras/{c}/camera_info",
                                    mask_topic=f"/cameras/{c}/mask") for c in ("front", "side")]
            with McapLog(log) as opened:
                frames = [f for f in FrameReader(opened, sensors, LogTopics()) if f.index in picks]
            row = [_tile(f.cameras[c].image, f.cameras[c].mask, f"{scene} {c} frame {f.index}")
                   for f in frames for c in ("front", "side")]
            rows.append(np.concatenate(row, axis=1))
    sheet = np.concatenate(rows, axis=0)
    ok, buf = cv2.imencode(".png", sheet[:, :, ::-1])
    if not ok:
        return 1
    args.out.write_bytes(buf.tobytes())
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]} px)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
