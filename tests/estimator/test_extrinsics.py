"""The camera extrinsics check (``estimator.extrinsics``): the known scene's outline against each
camera's first image, on the cube sample's first frame as recorded and with a camera turned."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.errors import ConfigError
from mvtop_cli.estimator import Estimator
from mvtop_cli.estimator.extrinsics import CameraAlignment, align_camera, check_camera, corrected_frame
from mvtop_cli.estimator.scene import SceneModel
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.track import extrinsics_report, run_summary

ROOT = Path(__file__).resolve().parents[2]


def _turn(deg) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_matrix(np.radians(np.asarray(deg, dtype=float)))
    return T


def _turned(frame, camera: str, deg):
    """``frame`` as a log whose ``camera`` is recorded turned by ``deg`` about its optical axes
    records it (``T_world_sensor @ Exp(turn)``, as scripts/perturb_extrinsics.py turns a log)."""
    img = frame.cameras[camera]
    return dataclasses.replace(frame, cameras={**frame.cameras, camera: dataclasses.replace(
        img, T_world_sensor=img.T_world_sensor @ _turn(deg))})


@pytest.fixture(scope="module")
def cube():
    """The cube config, its scene, its first two frames and a TF lookup."""
    cfg = load_config(ROOT / "configs" / "cube.yaml")
    with McapLog(ROOT / "sample_logs" / "cube.mcap") as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        frames = [f for f, _ in zip(reader, range(2))]
        tf = reader.tf
    return cfg, SceneModel(cfg, build_contact=False), frames, tf


def _check(cube, frame, camera, settings=None):
    cfg, scene, _, tf = cube
    img = frame.cameras[camera]
    return check_camera(scene, camera, img, frame.index, lambda f: tf.lookup("world", f, img.stamp_ns),
                        settings or cfg.extrinsics)


def test_the_recorded_cameras_line_up_with_their_images(cube):
    """As recorded (the simulator's true extrinsics), both cameras' best turns are under 0.05 deg,
    far below extrinsics.min_turn_deg, and add under 2 % to the outline score."""
    frame = cube[2][0]
    for camera in ("front", "side"):
        a = _check(cube, frame, camera)
        assert a is not None and a.samples > 2000
        assert a.angle_deg < 0.05 and a.gain < 0.02
        assert not a.misaligned and not a.corrected and not a.suspect


@pytest.mark.parametrize("deg", [(0.0, 1.0, 0.0), (2.0, 0.0, 0.0), (0.0, 0.0, 2.0), (1.2, -1.6, 0.8)],
                         ids=["1 deg about y", "2 deg about x", "2 deg about z (roll)", "2.15 deg oblique"])
def test_a_turned_camera_is_found_to_within_a_tenth_of_a_degree(cube, deg):
    """The front camera recorded turned 1-2 deg about any axis: the check finds that turn to
    within 0.1 deg (0.5 mm at 0.3 m), judges the camera misaligned and corrects it; the corrected
    pose is the camera's true one to the same precision, and the other camera stays as recorded."""
    frame = cube[2][0]
    wrong = _turned(frame, "front", deg)
    a = _check(cube, wrong, "front")
    assert a.misaligned and a.corrected and not a.at_edge and not a.suspect
    np.testing.assert_allclose(a.turn_deg, deg, atol=0.1)
    assert a.gain > 0.3
    fixed = corrected_frame(wrong, {"front": a, "side": _check(cube, wrong, "side")})
    error = se3.invert(frame.cameras["front"].T_world_sensor) @ fixed.cameras["front"].T_world_sensor
    assert np.degrees(se3.rotation_angle(error[:3, :3])) < 0.1
    np.testing.assert_array_equal(fixed.cameras["side"].T_world_sensor, frame.cameras["side"].T_world_sensor)


def test_warn_mode_and_a_turn_beyond_the_range_leave_the_camera_as_recorded(cube):
    """``extrinsics.mode: warn`` finds the same turn but corrects nothing (the run is suspect); a
    turn larger than ``range_deg`` ends on the range's edge and is never corrected."""
    cfg, _, frames, _ = cube
    wrong = _turned(frames[0], "front", (0.0, 2.0, 0.0))
    warned = _check(cube, wrong, "front", dataclasses.replace(cfg.extrinsics, mode="warn"))
    assert warned.misaligned and not warned.corrected and warned.suspect
    np.testing.assert_allclose(warned.turn_deg, (0.0, 2.0, 0.0), atol=0.1)
    assert corrected_frame(wrong, {"front": warned}) is wrong
    narrow = _check(cube, wrong, "front", dataclasses.replace(cfg.extrinsics, range_deg=1.0))
    assert narrow.at_edge and narrow.misaligned and not narrow.corrected and narrow.suspect
    assert "edge of the searched range" in narrow.warning()["detail"]


def _moved(frame, camera: str, shift_m):
    """``frame`` as a log whose ``camera`` is recorded moved by ``shift_m`` along its own axes."""
    img = frame.cameras[camera]
    T = np.eye(4)
    T[:3, 3] = shift_m
    return dataclasses.replace(frame, cameras={**frame.cameras, camera: dataclasses.replace(
        img, T_world_sensor=img.T_world_sensor @ T)})


def test_a_camera_moved_along_its_axis_is_not_corrected_by_a_turn(cube):
    """The front camera recorded 10 mm along its optical axis from where it was: a turn of about
    1 deg lines the board up, but the fingers line up on their own with a turn that moves their
    pixels by over 1 deg more, so more than a turn is off: misaligned, not corrected, the run
    suspect, and the warning says why. One moved 5 mm across its axis is much like a turn at the
    scene's depth: the meshes agree within ``mesh_tolerance_deg`` and it is corrected. A pure
    turn's meshes agree within 0.15 deg."""
    cfg, _, frames, _ = cube
    along = _check(cube, _moved(frames[0], "front", (0.0, 0.0, 0.01)), "front")
    assert along.misaligned and not along.one_turn and not along.corrected and along.suspect
    assert along.mesh_spread_deg > 1.0
    assert "line up with turns up to" in along.warning()["detail"]
    across = _check(cube, _moved(frames[0], "front", (0.005, 0.0, 0.0)), "front")
    assert across.misaligned and across.one_turn and across.corrected
    assert across.mesh_spread_deg <= cfg.extrinsics.mesh_tolerance_deg
    turned = _check(cube, _turned(frames[0], "front", (0.0, 2.0, 0.0)), "front")
    assert turned.mesh_spread_deg < 0.15


def test_too_few_scene_samples_are_not_judged(cube):
    """A camera whose image holds fewer than ``min_samples`` contour samples of the known scene
    is not judged (None), however it is turned."""
    cfg, _, frames, _ = cube
    wrong = _turned(frames[0], "front", (0.0, 2.0, 0.0))
    assert _check(cube, wrong, "front", dataclasses.replace(cfg.extrinsics, min_samples=10**6)) is None


def test_align_camera_finds_the_peak_of_a_smooth_score():
    """On a score peaked at (0.7, -1.3, 0.4) deg the search ends within its finest step; on a score
    that is flat it keeps turn 0 (ties go to the recorded extrinsics); a peak outside the range
    ends on its edge."""
    cfg = load_config(ROOT / "configs" / "cube.yaml").extrinsics
    peak = np.radians([0.7, -1.3, 0.4])

    def score(turns_rad):
        return -np.sum((turns_rad - peak) ** 2, axis=1)

    turn, value, edge = align_camera(score, cfg)
    np.testing.assert_allclose(turn, [0.7, -1.3, 0.4], atol=cfg.min_step_deg)
    assert value == pytest.approx(score(np.radians(turn)[None])[0]) and not edge
    turn, value, edge = align_camera(lambda t: np.zeros(len(t)), cfg)
    np.testing.assert_array_equal(turn, 0.0)
    assert value == 0.0 and not edge
    far = np.radians([6.0, 0.0, 0.0])
    turn, _, edge = align_camera(lambda t: -np.sum((t - far) ** 2, axis=1), cfg)
    assert edge and turn[0] == pytest.approx(cfg.range_deg)


def test_the_estimator_corrects_a_turned_camera_and_reports_it(cube):
    """Two frames of the cube sample with the front camera turned 2 deg: the first frame's check
    warns (camera_extrinsics, naming the camera and the turn), every frame carries the flag, the
    estimate is the one the log as recorded gives to within 0.5 mm, summary.json's ``extrinsics``
    holds both cameras' findings and no suspect_estimate is raised; with ``mode: warn`` the
    camera stays turned, the run is suspect and the covariance is the grasp prior's spread."""
    cfg, _, frames, tf = cube
    cfg = dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, num_particles=100))

    def run(config, turn_deg):
        est = Estimator.from_config(config, lambda fr, t: tf.lookup("world", fr, t))
        return [est.step(_turned(f, "front", turn_deg)) for f in frames]

    clean = run(cfg, (0.0, 0.0, 0.0))
    fixed = run(cfg, (0.0, 2.0, 0.0))
    assert [w["kind"] for w in clean[0].warnings if w["kind"] == "camera_extrinsics"] == []
    warned = [w for w in fixed[0].warnings if w["kind"] == "camera_extrinsics"]
    assert len(warned) == 1 and warned[0]["sensor"] == "front" and warned[0]["corrected"] is True
    assert "turned 2.0" in warned[0]["detail"] and "recalibrate" in warned[0]["detail"]
    assert not any(w["kind"] == "camera_extrinsics" for w in fixed[1].warnings)
    assert all("camera_extrinsics" in f.flags for f in fixed) and not any("camera_extrinsics" in f.flags for f in clean)
    offset = fixed[-1].T_world_object[:3, 3] - clean[-1].T_world_object[:3, 3]
    assert np.linalg.norm(offset) < 5e-4
    summary = run_summary(fixed, cfg, Path("cube.mcap"), 1.0, [])
    assert summary["extrinsics"]["front"]["corrected"] is True and summary["extrinsics"]["side"]["misaligned"] is False
    assert summary["extrinsics"]["front"]["turn_deg"][1] == pytest.approx(2.0, abs=0.1)
    assert "suspect_estimate" not in summary["warning_counts"]
    assert summary["suspect"]["raised"] is False and summary["suspect"]["causes"] == []

    left = run(dataclasses.replace(cfg, extrinsics=dataclasses.replace(cfg.extrinsics, mode="warn")), (0.0, 2.0, 0.0))
    summary = run_summary(left, cfg, Path("cube.mcap"), 1.0, [])
    assert summary["warning_counts"]["suspect_estimate"] == 1
    suspect = next(w for w in summary["warnings"] if w["kind"] == "suspect_estimate")
    assert "camera 'front'" in suspect["detail"] and "flag camera_extrinsics" in suspect["detail"]
    assert "camera_extrinsics" in summary["suspect"]["causes"] and summary["suspect"]["raised"] is True
    # the grasp prior's spread (3 mm half-width, uniform): a standard deviation of at least 3 / sqrt(3) mm
    def widest_m(frame):
        return np.sqrt(np.max(np.diag(frame.covariance)[:3]))

    assert widest_m(left[-1]) > 1.5e-3 > widest_m(fixed[-1])


def test_resume_carries_the_findings_and_the_correction(cube):
    """A run resumed after its first frame checks no camera again and keeps the correction: the
    second frame's estimate is the uninterrupted run's, bit for bit."""
    cfg, _, frames, tf = cube
    cfg = dataclasses.replace(cfg, filter=dataclasses.replace(cfg.filter, num_particles=50))
    wrong = [_turned(f, "front", (0.0, 2.0, 0.0)) for f in frames]
    est = Estimator.from_config(cfg, lambda fr, t: tf.lookup("world", fr, t))
    whole = [est.step(f) for f in wrong]
    resumed = Estimator.from_config(cfg, lambda fr, t: tf.lookup("world", fr, t))
    first = resumed.step(wrong[0])
    state = resumed.rng.bit_generator.state
    again = Estimator.from_config(cfg, lambda fr, t: tf.lookup("world", fr, t))
    again.resume_after(first)
    again.particles, again.rng.bit_generator.state = resumed.particles, state
    second = again.step(wrong[1])
    assert set(again.extrinsics) == {"front", "side"} and again.extrinsics["front"].corrected
    np.testing.assert_array_equal(second.T_world_object, whole[1].T_world_object)
    assert extrinsics_report(second) == extrinsics_report(whole[1])


def test_the_mode_is_checked_when_the_config_loads(tmp_path):
    text = (ROOT / "configs" / "cube.yaml").read_text() + "\nextrinsics:\n  mode: fix\n"
    (tmp_path / "meshes").symlink_to(ROOT / "configs" / "meshes")
    path = tmp_path / "cube.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"extrinsics\.mode"):
        load_config(path)


def test_a_record_of_a_corrected_camera_turns_it_back():
    """``corrected_pose`` undoes the turn the check found: a camera recorded at ``T @ Exp(t)``
    comes back to ``T``."""
    T = se3.make_pose(se3.rotvec_to_matrix(np.array([0.3, -0.2, 1.0])), np.array([0.1, 0.2, 0.3]))
    a = CameraAlignment("front", 0, (0.5, -1.0, 2.0), 1.0, 2.0, 300, False, 0.05, True, True, True)
    np.testing.assert_allclose(a.corrected_pose(T @ _turn((0.5, -1.0, 2.0))), T, atol=1e-12)


def test_a_rolled_camera_in_clutter_is_found_by_the_three_axis_start(tmp_path):
    """The hard scene's conn1 grasp 1012 (clutter, shadows) with its side camera recorded turned
    (-0.28, -1.72, -2.31) deg: the x/y grid alone lines the scene up on clutter 5.3 deg from the
    truth with its meshes agreeing (corrected wrong, before the three-axis start on the downsampled
    image); with it the turn is found to within 0.1 deg and corrected."""
    from mvtop_cli.pipelines.simulate import SimulateOptions, scene_options, simulate, write_scene_config
    from mvtop_cli.sim.episode import EpisodeOptions

    log = tmp_path / "log.mcap"
    simulate("conn1", 1012, log, scene_options(SimulateOptions(episode=EpisodeOptions(frames=4)), "hard"))
    cfg = load_config(write_scene_config("conn1", tmp_path / "config.yaml"))
    scene = SceneModel(cfg, build_contact=False)
    true_turn = (-0.28, -1.72, -2.31)
    with McapLog(log) as opened:
        reader = FrameReader(opened, sensor_topics(cfg), log_topics(cfg))
        frame = _turned(next(iter(reader)), "side", true_turn)
        img = frame.cameras["side"]
        a = check_camera(scene, "side", img, 0, lambda f: reader.tf.lookup("world", f, img.stamp_ns), cfg.extrinsics)
    assert a.misaligned and a.corrected
    np.testing.assert_allclose(a.turn_deg, true_turn, atol=0.1)
