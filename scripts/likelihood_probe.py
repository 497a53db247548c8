"""Where a frame's likelihood peaks along one end-effector axis, beside where the belief is.

Steps the estimator over a simulated log (the online API, so the same step as `mvtop estimate`)
and, at the frames asked for, scores the frame's likelihood at poses offset along the axis in
steps through the ground truth and through the estimate (log-likelihood and each sensor's IoU),
and the belief's particles (best and weighted mean log-likelihood). One JSON object per probed
frame and line ("around": "truth" or "estimate"), gzip-compressed.

Usage: .venv/bin/python scripts/likelihood_probe.py SCENE_DIR SEED FRAMES OUT.jsonl.gz
  [--modalities vision,tactile,contact] [--axis 0] [--half-width-mm 0.6] [--step-mm 0.02]
SCENE_DIR holds log.mcap and config.yaml (a benchmark folder's scenes/OBJECT_SEED); SEED is the
filter seed (the benchmark's runs use the grasp seed); FRAMES as `render-masks --frames`, e.g. 10-29 or 15,22,29.
"""

import argparse
import gzip
import json
from pathlib import Path

import numpy as np

from mvtop_cli.cli import parse_frames
from mvtop_cli.config import load_config
from mvtop_cli.errors import MvtopError
from mvtop_cli.estimator import Estimator
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import EstimateOptions, apply_options, log_topics, sensor_topics


def frames_arg(text: str) -> set[int]:
    try:
        return set(parse_frames(text))
    except MvtopError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("seed", type=int)
    ap.add_argument("frames", type=frames_arg)
    ap.add_argument("out", type=Path)
    ap.add_argument("--modalities", default="vision,tactile,contact")
    ap.add_argument("--axis", type=int, default=0, choices=(0, 1, 2), help="end-effector axis: 0 x, 1 y, 2 z")
    ap.add_argument("--half-width-mm", type=float, default=0.6)
    ap.add_argument("--step-mm", type=float, default=0.02)
    args = ap.parse_args()

    options = EstimateOptions(modalities=tuple(args.modalities.split(",")), seed=args.seed)
    cfg = apply_options(load_config(args.scene / "config.yaml"), options)
    offsets = np.arange(-args.half_width_mm, args.half_width_mm + args.step_mm / 2, args.step_mm) * 1e-3
    rows = []
    with McapLog(args.scene / "log.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda fr, t: reader.tf.lookup(cfg.frames.world, fr, t))
        for frame in reader:
            est = estimator.step(frame)
            if frame.index not in args.frames or frame.T_world_object_gt is None:
                continue
            likelihood = estimator.last_likelihood
            T_truth = np.linalg.inv(frame.T_world_ee) @ frame.T_world_object_gt
            particles = estimator.particles
            ll_particles = likelihood(particles.poses)
            for around, T0 in (("truth", T_truth), ("estimate", est.T_ee_object)):
                poses = np.repeat(T0[None], len(offsets), axis=0)
                poses[:, args.axis, 3] += offsets
                rows.append({
                    "frame": frame.index, "around": around, "axis": args.axis,
                    "offsets_mm": (offsets * 1e3).round(3).tolist(),
                    "log_lik": np.asarray(likelihood(poses)).round(3).tolist(),
                    "sensor_iou": [likelihood.sensor_ious(p) for p in poses],
                    "particles_ll_max": float(np.max(ll_particles)),
                    "particles_ll_wmean": float(np.sum(particles.weights() * ll_particles)),
                    "estimate_minus_truth_mm": ((est.T_ee_object[:3, 3] - T_truth[:3, 3]) * 1e3).round(3).tolist(),
                })
    with gzip.open(args.out, "wt") as fh:
        for row in rows:
            fh.write(json.dumps(row) + "\n")
    print(f"{len(rows)} rows -> {args.out}")


if __name__ == "__main__":
    main()
