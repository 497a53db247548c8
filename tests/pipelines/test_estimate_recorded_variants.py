"""The estimate stays accurate on logs recorded the way real ROS 2 setups record them.

Each variant is simulated (the cube, sample seed 1, 20 frames, JPEG quality 85 as the sample
logs), checked to be what it claims, estimated through ``estimate()`` with the written
config (500 particles, seed 0) and scored with the project's ``mvtop eval`` code against the
log's ground truth. The bound is the one the plain sample logs are held to
(tests/pipelines/test_estimate.py): final frame within 1 mm and 1 degree, modulo the part's
symmetries. The plug is estimated on the timing variant too, and a further object (conn2) on
one log that combines every variant.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.tf_buffer import TfBuffer
from mvtop_cli.pipelines.estimate import estimate
from mvtop_cli.pipelines.evaluate import evaluate
from mvtop_cli.pipelines.simulate import SimulateOptions, simulate, write_scene_config
from mvtop_cli.sim import robot
from mvtop_cli.sim.episode import EpisodeOptions
from mvtop_cli.sim.timing import SensorTiming

FRAMES = 20
PERIOD_NS = 100_000_000  # 10 Hz frames
DISTORTION = (-0.25, 0.08, 0.001, -0.0005, -0.01)  # plumb_bob k1 k2 p1 p2 k3
TIMING = SensorTiming(camera_every=2, drop_fraction=0.1, jitter_s=0.008)
VARIANTS = {
    "raw_images": ("cube", dict(image_format="raw", tactile_format="raw")),
    "lens_distortion": ("cube", dict(distortion=DISTORTION)),
    "tf_chain": ("cube", dict(kinematics="tf-chain")),
    "joint_states_urdf": ("cube", dict(kinematics="joint-states")),
    "rates_drops_jitter": ("cube", dict(timing=TIMING)),
    # the plug's large faces leave its rotation to the cameras: frames with tactile images
    # only must not pull it (they did, 1.75 deg at 30 frames, while they were scored as a
    # whole frame of evidence)
    "rates_drops_jitter_plug": ("plug", dict(timing=TIMING)),
    "all_combined": (
        "conn2", dict(image_format="raw", distortion=DISTORTION, kinematics="joint-states", timing=TIMING)
    ),
}
IMAGE_TOPICS = ("/cameras/front/image", "/cameras/side/image", "/tactile/left/image", "/tactile/right/image")
@dataclass
class Run:
    name: str
    log: Path
    config: Path
    summary: dict
    report: dict


@pytest.fixture(scope="module", params=list(VARIANTS))
def run(request, tmp_path_factory) -> Run:
    """Simulate, estimate and evaluate one variant (once per module)."""
    obj, kw = VARIANTS[request.param]
    d = tmp_path_factory.mktemp(request.param)
    options = SimulateOptions(episode=EpisodeOptions(frames=FRAMES), jpeg_quality=85, **kw)
    simulate(obj, 1, d / "log.mcap", options)
    cfg_path = write_scene_config(obj, d / "config.yaml", options)
    summary = estimate(d / "log.mcap", load_config(cfg_path), d / "track")
    report = evaluate(d / "track", d / "log.mcap", None, d / "eval")
    return Run(request.param, d / "log.mcap", cfg_path, summary, report)


def _topic_types(log: Path) -> dict[str, str]:
    with McapLog(log) as mlog:
        s = mlog.summary()
        return {t: s.topic(t).type for t in s.topic_names}


def _tf(log: Path) -> TfBuffer:
    tf = TfBuffer(source=str(log))
    with McapLog(log) as mlog:
        topics = [t for t in ("/tf", "/tf_static") if mlog.summary().has_topic(t)]
        for m in mlog.messages(topics):
            tf.add_tf_message(m.msg, static=m.topic == "/tf_static")
    return tf


def _stamps(log: Path, topic: str) -> np.ndarray:
    with McapLog(log) as mlog:
        return np.array([m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec for m in mlog.messages(topic)])


def _check_raw(r: Run) -> None:
    types = _topic_types(r.log)
    images = [t for t in IMAGE_TOPICS if r.name == "raw_images" or t.startswith("/cameras")]
    assert all(types[t] == "sensor_msgs/msg/Image" for t in images), types
    assert not any(t.startswith("/cameras") and t.endswith("compressed") for t in types), types


def _check_distortion(r: Run) -> None:
    for cam in ("front", "side"):
        with McapLog(r.log) as mlog:
            info = next(mlog.messages(f"/cameras/{cam}/camera_info")).msg
        assert info.distortion_model == "plumb_bob"
        np.testing.assert_allclose(info.d, DISTORTION)


def _check_tf_chain(r: Run) -> None:
    tf = _tf(r.log)
    chain, frame = ["ee"], "ee"
    while tf.parent(frame) is not None:
        frame = tf.parent(frame)
        chain.append(frame)
    assert chain == ["ee", "tool0", "flange", "wrist_pitch", "wrist_yaw", "gantry_z", "gantry_y", "gantry_x",
                     "base_link", "world"]
    static = [tf.is_static(p, c) for c, p in zip(chain[:-1], chain[1:])]
    assert static == [True, True, False, False, False, False, False, False, True]
    assert tf.parent("finger_left") == "ee" and not tf.is_static("ee", "finger_left")


def _check_joint_states(r: Run) -> None:
    types = _topic_types(r.log)
    assert "/tf" not in types  # no end-effector (or any robot) TF: only /tf_static's calibration
    tf = _tf(r.log)
    assert tf.frames == {"world", "front_optical", "side_optical", "base_link"}
    cfg = load_config(r.config)
    assert cfg.robot.urdf is not None and cfg.robot.urdf.is_file()
    with McapLog(r.log) as mlog:
        names = list(next(mlog.messages("/joint_states")).msg.name)
    assert names == list(robot.ARM_JOINTS + robot.FINGER_JOINTS)


def _check_timing(r: Run) -> None:
    types = _topic_types(r.log)
    suffix = {t: "" if types.get(t) else "/compressed" for t in IMAGE_TOPICS}
    counts = {t: len(_stamps(r.log, t + suffix[t])) for t in IMAGE_TOPICS}
    cams, tacs = [counts[t] for t in IMAGE_TOPICS[:2]], [counts[t] for t in IMAGE_TOPICS[2:]]
    assert max(cams) <= FRAMES // 2 and min(tacs) > max(cams), counts  # cameras at half the tactile rate
    assert sum(cams) + sum(tacs) < FRAMES + 2 * FRAMES  # some images were dropped
    gt = _stamps(r.log, "/ground_truth/object_pose")
    nominal = gt[1:-1]  # the robot's streams add a held sample before and after the frames
    assert len(nominal) == FRAMES
    for t in IMAGE_TOPICS:
        s = _stamps(r.log, t + suffix[t])
        offsets = (s - nominal[0] + PERIOD_NS // 2) % PERIOD_NS - PERIOD_NS // 2
        assert np.all(np.abs(offsets) <= 8_000_000) and np.any(offsets != 0), (t, offsets)


CHECKS = {
    "raw_images": [_check_raw],
    "lens_distortion": [_check_distortion],
    "tf_chain": [_check_tf_chain],
    "joint_states_urdf": [_check_joint_states],
    "rates_drops_jitter": [_check_timing],
    "rates_drops_jitter_plug": [_check_timing],
    "all_combined": [_check_raw, _check_distortion, _check_joint_states, _check_timing],
}


@pytest.mark.slow
def test_variant_is_what_it_claims(run):
    for check in CHECKS[run.name]:
        check(run)


@pytest.mark.slow
def test_final_error_within_the_sample_logs_bound(run):
    """Final frame within 1 mm and 1 degree of the truth (the bound of the plain sample logs)."""
    final = run.report["final"]
    trans, rot = final["translation_error_mm"], final["rotation_error_deg"]
    print(f"{run.name}: final error {trans:.3f} mm {rot:.3f} deg, {run.summary['frames_processed']} frames "
          f"in {run.summary['run_time_s']:.1f} s")
    assert run.summary["frames_processed"] >= FRAMES - 2
    assert trans < 1.0, f"{run.name}: final translation error {trans:.3f} mm"
    assert rot < 1.0, f"{run.name}: final rotation error {rot:.3f} deg"
