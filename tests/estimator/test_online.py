"""The online API: an ``Estimator`` built from a config and fed one frame at a time gives the
track ``mvtop estimate`` writes for the same frames."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.estimator import Estimator, FrameEstimate
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate, log_topics, sensor_topics
from mvtop_cli.pipelines.track import TRACK_CSV_HEADER, track_csv_row
from mvtop_cli.records import Frame

ROOT = Path(__file__).resolve().parents[2]
FRAMES = 6


def test_online_steps_give_the_offline_track(tmp_path):
    log_path = ROOT / "sample_logs" / "conn2.mcap"
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    cfg = replace(cfg, filter=replace(cfg.filter, num_particles=120))
    estimate(log_path, cfg, tmp_path / "offline", EstimateOptions(max_frames=FRAMES))
    offline = (tmp_path / "offline" / "track.csv").read_text().splitlines()

    rows = [TRACK_CSV_HEADER]
    with McapLog(log_path) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        # the fingers occlude the part: their TF frames come from the log's TF, as a robot's tf2 buffer would
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        for frame, _ in zip(reader, range(FRAMES)):
            assert isinstance(frame, Frame)
            result = estimator.step(frame)
            assert isinstance(result, FrameEstimate) and result.covariance.shape == (6, 6)
            assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
            rows.append(track_csv_row(result))
    assert rows == offline
    assert len(rows) == FRAMES + 1


def test_moving_occluders_need_a_frame_pose():
    """A config with a gripper-mounted mesh asks for ``frame_pose`` when it is first needed,
    naming the TF frame."""
    cfg = load_config(ROOT / "configs" / "cube.yaml")
    moving = [e.frame for e in cfg.environment if e.occlude and e.frame != cfg.frames.world]
    assert moving == ["finger_left", "finger_right"]
    estimator = Estimator.from_config(replace(cfg, modalities=("vision",)))
    with McapLog(ROOT / "sample_logs" / "cube.mcap") as log:
        frame = next(iter(FrameReader(log, sensor_topics(cfg), log_topics(cfg))))
    with pytest.raises(ValueError, match=f"TF frame {moving[0]!r}: give the Estimator a frame_pose"):
        estimator.step(frame)


def _vision_only_steps(threshold: float | None) -> list[FrameEstimate]:
    """Eight frames of the shaft peg sample with the cameras alone (they cannot see its roll
    about its long axis), 120 particles, ``output.suspect_unpinned_fraction`` = ``threshold``."""
    cfg = load_config(ROOT / "configs" / "shaft_peg.yaml")
    cfg = replace(cfg, modalities=("vision",), filter=replace(cfg.filter, num_particles=120),
                  output=replace(cfg.output, suspect_unpinned_fraction=threshold))
    with McapLog(ROOT / "sample_logs" / "shaft_peg.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        estimator = Estimator.from_config(cfg, frame_pose=lambda name, t: reader.tf.lookup("world", name, t))
        return [estimator.step(frame) for frame, _ in zip(reader, range(8))]


def test_a_suspect_frame_reports_the_grasp_priors_spread():
    """Once the frames whose evidence left some pose axis open reach the share
    ``output.suspect_unpinned_fraction``, each further frame is flagged ``suspect_estimate`` and its
    covariance holds the grasp prior's whole spread on every axis; the estimates are unchanged."""
    from mvtop_cli.estimator.prior import GraspPriorModel

    plain, watched = _vision_only_steps(None), _vision_only_steps(0.1)
    cfg = load_config(ROOT / "configs" / "shaft_peg.yaml")
    prior_var = GraspPriorModel(cfg.grasp_prior, cfg.search.bound).sigma ** 2
    open_so_far = np.cumsum([not r.evidence.pinned for r in plain])
    assert [r.unpinned for r in watched] == [(int(k), i + 1) for i, k in enumerate(open_so_far)]
    assert 0 < open_so_far[-1] < 8  # this log has both kinds of frame
    for p, w, k in zip(plain, watched, open_so_far):
        np.testing.assert_array_equal(w.T_ee_object, p.T_ee_object)
        assert "suspect_estimate" not in p.flags
        suspect = k / (w.index + 1) >= 0.1
        assert ("suspect_estimate" in w.flags) == suspect
        if suspect:
            assert np.all(np.diag(w.covariance) >= prior_var)
            # the axes the frame pinned widen to the prior's spread; an open one had it already
            assert np.all(np.diag(w.covariance) >= np.diag(p.covariance))
            assert np.any(np.diag(w.covariance) > np.diag(p.covariance))
        else:
            np.testing.assert_array_equal(w.covariance, p.covariance)
