"""How much the camera evidence follows the belief (issue: evidence from the image, the belief only
chooses). For frames 5 and 22 of each sample log: the observed camera masks made from a belief
at the truth and from three beliefs 3-5 mm / 3-5 deg off it (seeded), each against the true
silhouette, counting truth outside the ROI as missed. Prints the IoUs per camera.
Usage: .venv/bin/python scripts/camera_evidence_probe.py [prior|belief]  (masking.grabcut_prompt;
default: the config's)"""
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mvtop_cli.config import load_config
from mvtop_cli.estimator.observation import ObservationModel
from mvtop_cli.estimator.prior import init_from_prior
from mvtop_cli.estimator.scene import OBJECT_ID, SceneModel
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.se3 import perturb_about_origin
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.render.roi import Roi

ROOT = Path(__file__).resolve().parents[1]
rng = np.random.default_rng(7)
for name in ("cube", "shaft_peg", "plug", "conn1", "conn2"):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    if len(sys.argv) > 1:
        cfg = replace(cfg, masking=replace(cfg.masking, grabcut_prompt=sys.argv[1]))
    scene = SceneModel(cfg, build_contact=False)
    with McapLog(ROOT / "sample_logs" / f"{name}.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        model = ObservationModel(cfg, scene, lambda fr, t, reader=reader: reader.tf.lookup("world", fr, t))
        for frame in reader:
            if frame.index not in (5, 22):
                continue
            T_gt = se3.invert(frame.T_world_ee) @ frame.T_world_object_gt
            rows = []
            for trial in range(4):
                if trial == 0:
                    centre = T_gt
                else:
                    d = rng.normal(size=3)
                    d *= rng.uniform(3e-3, 5e-3) / np.linalg.norm(d)
                    w = rng.normal(size=3)
                    w *= np.radians(rng.uniform(3, 5)) / np.linalg.norm(w)
                    centre = perturb_about_origin(T_gt, d, w)
                belief = init_from_prior(centre, 3e-4, np.radians(0.3), 200, np.random.default_rng(trial))
                obs = model.observe(frame, belief, converged=False)
                ious = {}
                for cam in frame.cameras:
                    img = frame.cameras[cam]
                    truth = scene.renderer.render_masks(OBJECT_ID, frame.T_sensor_object(cam, T_gt)[None], img.camera,
                                                        Roi.full(img.camera), obs.occluders[cam])[0]
                    ious[cam] = obs.iou_with(cam, truth)
                rows.append(ious)
            cams = list(rows[0])
            parts = [f"{c}: truth-start {rows[0][c]:.3f} offset-starts " + "/".join(f"{r[c]:.3f}" for r in rows[1:])
                     for c in cams]
            print(name, "frame", frame.index, " ".join(parts), flush=True)
