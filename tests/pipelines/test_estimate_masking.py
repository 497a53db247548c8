"""Masking choices of the config reach the estimator: the promptable mode switches on once the
belief has converged, and only when the config asks for it."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]


def _modes(out: Path) -> list[str]:
    with (out / "track.csv").open() as fh:
        return [row["mask_mode"] for row in csv.DictReader(fh)]


def test_prompt_mode_only_when_configured_and_converged(tmp_path):
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    opts = EstimateOptions(modalities=("vision", "tactile"), num_particles=150, max_frames=8)
    estimate(ROOT / "sample_logs" / "conn2.mcap", cfg, tmp_path / "off", opts)
    assert set(_modes(tmp_path / "off")) == {"proposals"}
    on = replace(cfg, masking=replace(cfg.masking, prompt_when_converged=True))
    summary = estimate(ROOT / "sample_logs" / "conn2.mcap", on, tmp_path / "on", opts)
    modes = _modes(tmp_path / "on")
    assert modes[0] == "proposals" and "prompt" in modes  # the first frame is never converged
    assert summary["frames_processed"] == 8


def test_frames_with_a_missing_sensor_still_update(tmp_path):
    """Drop the side camera's image in frames 1-3 and a tactile image in frame 4: every frame
    is still estimated, with the sensors it has."""
    from mvtop_cli.estimator import Estimator
    from mvtop_cli.estimator.scene import SceneModel
    from mvtop_cli.io.frames import FrameReader
    from mvtop_cli.io.mcap_reader import McapLog
    from mvtop_cli.io.mcap_writer import LogWriter
    from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

    src = ROOT / "sample_logs" / "conn2.mcap"
    gappy = tmp_path / "gappy.mcap"
    t0 = 1_700_000_000_000_000_000
    drop = {("/cameras/side/image/compressed", k) for k in (1, 2, 3)} | {
        ("/tactile/left/depth", 4), ("/tactile/left/image/compressed", 4)
    }
    with McapLog(src) as log, LogWriter(gappy) as w:
        for m in log.messages(decode=False):
            k = round((m.log_time_ns - t0) / 1e8)
            if (m.topic, k) not in drop:
                w.write_raw(m.topic, m.type, m.msg, m.log_time_ns, m.publish_time_ns)
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=100))
    with McapLog(gappy) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        est = Estimator(cfg, SceneModel(cfg), lambda f, t: reader.tf.lookup("world", f, t))
        results = [est.step(fr) for fr, _ in zip(reader, range(6))]
    sensors = [set(r.sensors) for r in results]
    assert sensors[0] == {"front", "side", "left", "right"}
    assert sensors[1] == sensors[2] == sensors[3] == {"front", "left", "right"}
    assert sensors[4] == {"front", "side", "right"}
    assert all(np.isfinite(r.T_world_object).all() for r in results)


def _first_frame_estimator(cfg):
    from mvtop_cli.estimator import Estimator
    from mvtop_cli.estimator.scene import SceneModel
    from mvtop_cli.io.frames import FrameReader
    from mvtop_cli.io.mcap_reader import McapLog
    from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

    with McapLog(ROOT / "sample_logs" / "conn2.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        est = Estimator(cfg, SceneModel(cfg), lambda f, t: reader.tf.lookup("world", f, t))
        result = est.step(next(iter(reader)))
    return est, result


def test_a_sensor_with_weight_zero_is_switched_off():
    """``weight: 0`` removes a camera from eq. 2 (it used to fall back to the default share);
    the other sensors keep their default shares, and the likelihood is exactly their
    weighted IoU sum over the temperature."""
    from mvtop_cli.estimator.prior import init_uniform_box

    base = load_config(ROOT / "configs" / "conn2.yaml")
    # conn2's config scales a camera with a small mask down (filter.camera_full_weight_px): off, so
    # every sensor keeps its default share
    base = replace(base, filter=replace(base.filter, num_particles=100, camera_full_weight_px=0.0))
    assert base.sensors.cameras[0].name == "front"
    off = replace(base, sensors=replace(base.sensors, cameras=(replace(base.sensors.cameras[0], weight=0.0),
                                                               *base.sensors.cameras[1:])))
    poses = init_uniform_box(base.grasp_prior.pose.matrix(), 0.002, np.radians(5.0), 12, np.random.default_rng(3)).poses
    tau = base.filter.temperature
    for cfg, front_weight in ((base, 0.25), (off, 0.0)):
        est, result = _first_frame_estimator(cfg)
        assert not result.contact
        assert result.sensors == ("left", "right", "front", "side")
        iou_t, iou_v = est.last_likelihood.ious(poses)
        expected = (0.25 * iou_t.sum(axis=1) + front_weight * iou_v[:, 0] + 0.25 * iou_v[:, 1]) / tau
        assert np.ptp(iou_v[:, 0]) > 0.05  # the front camera's IoU does vary over these poses
        np.testing.assert_allclose(est.last_likelihood(poses), expected, rtol=1e-12, atol=1e-12)


def test_every_sensor_at_weight_zero_is_refused(tmp_path):
    import yaml

    from mvtop_cli.errors import ConfigError

    data = yaml.safe_load((ROOT / "configs" / "conn2.yaml").read_text())
    for kind in ("cameras", "tactile"):
        for s in data["sensors"][kind]:
            s["weight"] = 0.0
    path = tmp_path / "conn2.yaml"
    path.write_text(yaml.safe_dump(data))
    (tmp_path / "meshes").symlink_to(ROOT / "configs" / "meshes")
    with pytest.raises(ConfigError, match=r"conn2\.yaml: sensors: every sensor has weight 0"):
        load_config(path)
