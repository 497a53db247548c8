"""Closed-loop insertion with the simulated sensors: the estimator gets exactly the frames the
kept log gives back, every attempt is a log, and the filter in the loop is deterministic."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.insertion import InsertionOptions, insert, method_config
from mvtop_cli.pipelines.simulate import SimulateOptions, scene_options, write_scene_config
from mvtop_cli.sim.closed_loop import ControllerOptions, ground_truth_estimator
from mvtop_cli.sim.episode import apply_offset

SMALL = InsertionOptions(sensors=SimulateOptions(width=320, height=240))


def test_estimator_sees_the_frames_the_kept_logs_hold(tmp_path):
    cfg = load_config(write_scene_config("conn2", tmp_path / "scene" / "config.yaml"))
    seen = []
    truth = ground_truth_estimator()
    wrong = se3.make_pose(np.eye(3), [0.0005, 0.0, 0.0])  # twice conn2's clearance: the first attempt stalls

    def estimate(frame, state):
        seen.append(frame)
        return truth(frame, state) if any(f.contact for f in seen) else apply_offset(wrong, state.T_ee_object)

    result = insert("conn2", 3, None, SMALL, log_dir=tmp_path / "logs", estimator=estimate)
    assert [a.outcome for a in result.attempts] == ["stalled", "inserted"]
    assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == ["attempt_1.mcap", "attempt_2.mcap"]
    assert len(seen) == result.frames
    for attempt in result.attempts:
        with McapLog(tmp_path / "logs" / f"attempt_{attempt.index}.mcap") as log:
            frames = list(FrameReader(log, sensor_topics(cfg), log_topics(cfg)))
            gt = [m for m in log.messages(["/ground_truth/object_pose"])]
        assert len(frames) == attempt.last_frame - attempt.first_frame + 1 == len(gt)
        for got, fed in zip(frames, seen[attempt.first_frame:attempt.last_frame + 1]):
            assert got.stamp_ns == fed.stamp_ns and got.contact == fed.contact
            assert np.allclose(got.T_world_ee, fed.T_world_ee, atol=1e-9)
            assert fed.T_world_object_gt is None  # the estimator gets no ground truth
            assert set(got.cameras) == set(fed.cameras) == {"front", "side"}
            assert set(got.tactile) == set(fed.tactile) == {"left", "right"}
            for name in ("front", "side", "left", "right"):
                a, b = got.image(name), fed.image(name)
                assert np.array_equal(a.image, b.image)  # the decoded jpeg, as the log reader gives it
                assert np.allclose(a.T_world_sensor, b.T_world_sensor, atol=1e-9)
                assert (a.depth is None) == (b.depth is None)
                if a.depth is not None:
                    assert np.array_equal(a.depth, b.depth)


def test_filter_in_the_loop_same_seed_same_result(tmp_path):
    cfg = load_config(write_scene_config("conn2", tmp_path / "config.yaml"))
    cfg = method_config(cfg, ("tactile", "contact"), 30, 1000)
    opts = replace(SMALL, controller=ControllerOptions(attempts=2))
    a = insert("conn2", 1000, cfg, opts)
    b = insert("conn2", 1000, cfg, opts)
    assert a.attempts == b.attempts and a.success == b.success and a.frames == b.frames
    assert all(np.array_equal(x.T_world_ee, y.T_world_ee) for x, y in zip(a.states, b.states))
    assert 1 <= len(a.attempts) <= 2
    assert a.attempts[0].align_error_m < 0.003  # the filter, not the nominal grasp, placed the part


@pytest.mark.parametrize("modalities, cameras, tactile", [
    (("vision",), {"front", "side"}, set()),
    (("tactile", "contact"), set(), {"left", "right"}),
])
def test_the_filter_sees_only_the_sensors_of_its_modalities(tmp_path, monkeypatch, modalities, cameras, tactile):
    import mvtop_cli.pipelines.insertion as ins

    cfg = method_config(load_config(write_scene_config("conn2", tmp_path / "config.yaml")), modalities, 30, 1)
    seen = []

    def step(self, frame):
        seen.append((set(frame.cameras), set(frame.tactile)))
        return SimpleNamespace(T_ee_object=cfg.grasp_prior.pose.matrix())

    monkeypatch.setattr(ins.Estimator, "step", step)
    result = insert("conn2", 1, cfg, replace(SMALL, controller=ControllerOptions(attempts=1)))
    assert len(seen) == result.frames and set(map(frozenset, (c for c, _ in seen))) == {frozenset(cameras)}
    assert all(t == tactile for _, t in seen)


def test_a_hard_scene_changes_the_camera_images_not_the_motion():
    """With the true pose as the estimate the motion does not depend on the images: the hard
    scene (``simulate.scene_options``) gives the same states and tactile frames, other camera images."""
    seen: dict[str, list] = {"default": [], "hard": []}

    def recording(scene):
        truth = ground_truth_estimator()

        def estimate(frame, state):
            seen[scene].append(frame)
            return truth(frame, state)

        return estimate

    one = replace(SMALL, controller=ControllerOptions(attempts=1))
    a = insert("conn2", 5, None, one, estimator=recording("default"))
    b = insert("conn2", 5, None, replace(one, sensors=scene_options(one.sensors, "hard")), estimator=recording("hard"))
    assert a.success and b.success and a.frames == b.frames == len(seen["default"]) == len(seen["hard"])
    assert all(np.array_equal(x.T_world_ee, y.T_world_ee) and np.array_equal(x.T_ee_object, y.T_ee_object)
               for x, y in zip(a.states, b.states))
    for fa, fb in zip(seen["default"], seen["hard"]):
        for side in ("left", "right"):  # the gel sees depth only: lights and clutter do not reach it
            assert np.array_equal(fa.image(side).image, fb.image(side).image)
        for cam in ("front", "side"):
            diff = np.abs(fa.image(cam).image.astype(np.int16) - fb.image(cam).image.astype(np.int16))
            assert diff.mean() > 20.0  # shadows, clutter, glossy plastic and changing lights [DN]


@pytest.mark.parametrize("fmt", ["raw", "png"])
def test_recorded_masks_reach_the_estimator_as_the_kept_log_holds_them(tmp_path, fmt):
    """With a simulated segmenter (``SimulateOptions.mask_topics``) each camera frame carries its
    recorded object mask, the one the kept log gives back through the scene's ``mask_topic``."""
    sensors = replace(SMALL.sensors, mask_topics=True, mask_format=fmt)
    cfg = load_config(write_scene_config("conn2", tmp_path / "scene" / "config.yaml", sensors))
    assert cfg.masking.camera.backend == "topic"
    seen = []
    truth = ground_truth_estimator()

    def estimate(frame, state):
        seen.append(frame)
        return truth(frame, state)

    opts = InsertionOptions(sensors=sensors, controller=ControllerOptions(attempts=1))
    result = insert("conn2", 3, None, opts, log_dir=tmp_path / "logs", estimator=estimate)
    assert result.success and len(seen) == result.frames
    with McapLog(tmp_path / "logs" / "attempt_1.mcap") as log:
        frames = list(FrameReader(log, sensor_topics(cfg), log_topics(cfg)))
    assert len(frames) == len(seen)
    for got, fed in zip(frames, seen):
        for cam in ("front", "side"):
            mask = fed.image(cam).mask
            assert mask is not None and mask.dtype == np.uint16 and mask.shape == (240, 320)
            assert np.array_equal(mask, got.image(cam).mask)
    assert all(np.count_nonzero(f.image("front").mask) > 50 for f in seen)  # the part is in view
