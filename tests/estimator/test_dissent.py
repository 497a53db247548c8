"""The dissent search (``Estimator._dissent_search``, ``search.dissent``): a sensor outvoted by
the others gets the poses it explains tried before the consistency watch scales it down.

The scene is a simulated shaft-peg grasp (seed 1001) whose first-frame searches settle 12-19
deg off the truth: the left pad's contact (IoU 0.99 at the truth, 0.46 at that mode) rises only
within a fraction of a millimetre of the truth, so the joint searches miss it, and the camera
evidence agrees with the wrong mode. With camera masks prompted by the grasp prior (the belief
only chooses) the dissent search finds the truth's basin within a frame; without it the pad is
scaled down after five frames and the run ends in the wrong mode.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.estimator import Estimator
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.simulate import SimulateOptions, simulate, write_scene_config
from mvtop_cli.sim.episode import EpisodeOptions

SEED = 1001
FRAMES = 8


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("shaft_peg_1001")
    options = SimulateOptions(episode=EpisodeOptions(frames=30))
    simulate("shaft_peg", SEED, d / "log.mcap", options)
    cfg = load_config(write_scene_config("shaft_peg", d / "config.yaml", options))
    return d / "log.mcap", replace(cfg, filter=replace(cfg.filter, seed=SEED),
                                   masking=replace(cfg.masking, grabcut_prompt="prior"))


def _track(log_path, cfg):
    """Per frame of the first ``FRAMES``: (translation error [mm], rotation error [deg], flags,
    the left pad's IoU at the estimate)."""
    out = []
    with McapLog(log_path) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        for frame, _ in zip(reader, range(FRAMES)):
            r = estimator.step(frame)
            T_gt = se3.invert(frame.T_world_ee) @ frame.T_world_object_gt
            dt = np.linalg.norm(r.T_ee_object[:3, 3] - T_gt[:3, 3]) * 1e3
            dw = np.degrees(np.linalg.norm(se3.matrix_to_rotvec(r.T_ee_object[:3, :3] @ T_gt[:3, :3].T)))
            out.append((dt, dw, r.flags, r.sensor_iou["left"]))
    return out


def test_an_outvoted_pad_draws_the_estimate_out_of_a_wrong_mode(scene):
    log_path, cfg = scene
    with_dissent = _track(log_path, cfg)
    assert with_dissent[0][1] > 10.0  # the first frame's searches miss the truth
    assert with_dissent[0][3] < 0.6  # and the left pad says so
    assert any("re_searched" in flags for _, _, flags, _ in with_dissent[1:3])
    for dt, dw, flags, left in with_dissent[3:]:
        assert dw < 2.0 and dt < 1.2, with_dissent
        assert left > 0.9 and "sensor_downweighted" not in flags

    without = _track(log_path, replace(cfg, search=replace(cfg.search, dissent=False)))
    assert all(dw > 10.0 for _, dw, _, _ in without), without
    assert any("sensor_downweighted" in flags for _, _, flags, _ in without)
