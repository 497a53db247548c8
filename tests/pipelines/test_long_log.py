"""Memory does not grow with the number of frames: reading and grouping a log keeps a bounded
window of images, and ``estimate`` keeps no per-frame result in memory (they go to the
checkpoint journal). The gigabyte-scale figures come from ``mvtop benchmark long-log``."""

from __future__ import annotations

import csv
import gc
import tracemalloc
from pathlib import Path

import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.estimator import FrameEstimate
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.io.frames import FrameReader, LogTopics, SensorTopics
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000_000_000_000
DT = 100_000_000  # 10 Hz [ns]
W, H = 160, 120
IMAGE_BYTES = W * H * 3
CAMERA = PinholeCamera(width=W, height=H, K=np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1.0]]))
SENSORS = [SensorTopics.default("front"), SensorTopics.default("side")]


def write_log(path: Path, frames: int) -> None:
    """``frames`` frames of two raw rgb8 cameras (smooth images: the file stays small, the
    decoded images do not), a moving end effector and a contact flag."""
    with LogWriter(path, compression="zstd") as w:
        T_front = se3.make_pose(np.eye(3), [0.0, 0.0, -0.5])
        T_side = se3.make_pose(np.eye(3), [0.1, 0.0, -0.5])
        w.write_tf([("world", "front_optical", T_front), ("world", "side_optical", T_side)], T0, static=True)
        for k in range(frames):
            t = T0 + k * DT
            w.write_tf([("world", "ee", se3.make_pose(np.eye(3), [0.001 * k, 0.0, 0.3]))], t)
            w.write_bool("/contact", k % 7 == 0, t)
            for name in ("front", "side"):
                img = np.full((H, W, 3), k % 251, dtype=np.uint8)
                w.write_image(f"/cameras/{name}/image", img, t, f"{name}_optical")
                w.write_camera_info(f"/cameras/{name}/camera_info", CAMERA, t, f"{name}_optical")


def peak_while_reading(path: Path) -> tuple[int, int]:
    """(frames read, tracemalloc peak [bytes]) over reading and grouping every frame of ``path``."""
    tracemalloc.start()
    try:
        n = 0
        with McapLog(path) as log:
            for frame in FrameReader(log, SENSORS, LogTopics(ground_truth=None, joint_states=None)):
                assert frame.cameras["front"].image.shape == (H, W, 3)
                n += 1
        return n, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_reading_a_long_log_keeps_a_bounded_window_of_images(tmp_path):
    short, long = tmp_path / "short.mcap", tmp_path / "long.mcap"
    write_log(short, 30)
    write_log(long, 300)
    peak_while_reading(short)  # warm up: decoders, imports
    n_short, peak_short = peak_while_reading(short)
    n_long, peak_long = peak_while_reading(long)
    assert (n_short, n_long) == (30, 300)
    per_frame = 2 * IMAGE_BYTES
    # Ten times the frames; had the reader kept each frame's images, the peak would grow by
    # 270 frames of images (31 MB). It may grow by a few frames' worth (TF arrays, chunks).
    assert peak_long - peak_short < 5 * per_frame, (peak_short, peak_long)
    assert peak_long < 40 * per_frame, peak_long


def test_estimate_keeps_no_per_frame_result_in_memory(tmp_path):
    cfg = load_config(ROOT / "configs" / "cube.yaml")
    live: list[int] = []

    def count_results(done: int, total: int) -> None:
        gc.collect()
        live.append(sum(isinstance(o, FrameEstimate) for o in gc.get_objects()))

    out = tmp_path / "out"
    summary = estimate(ROOT / "sample_logs" / "cube.mcap", cfg, out, EstimateOptions(num_particles=30, max_frames=6),
                       progress=count_results)
    assert len(live) == 7  # before the first frame, then after each
    assert max(live) <= 1, live  # at most the frame just estimated, whatever the frame count
    assert summary["frames_processed"] == 6
    with open(out / "track.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in rows] == list(range(6))
