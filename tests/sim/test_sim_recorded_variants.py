"""The simulator's recording variants: the gantry robot's kinematics and URDF, the sensor
timing schedule, and logs that read back to the same frames as the plain log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from mvtop_cli.cli import cli
from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.urdf import UrdfKinematics
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.simulate import URDF_FILE, SimulateOptions, scene_config, simulate, write_scene_config
from mvtop_cli.sim import gripper as grip
from mvtop_cli.sim import robot
from mvtop_cli.sim.episode import EpisodeOptions, EpisodeState, state_at
from mvtop_cli.sim.timing import SensorTiming, capture_schedule

SENSORS = [("front", "camera"), ("side", "camera"), ("left", "tactile"), ("right", "tactile")]
STAMPS = [1_000_000_000 + k * 100_000_000 for k in range(400)]


def _ee_poses(n: int, seed: int = 0) -> np.ndarray:
    """Gripper-down end-effector poses around the work cell's receptacle, like the episodes'."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("xyz", np.column_stack([
        np.pi + rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-np.pi / 2, np.pi / 2, n),
    ])).as_matrix()
    return se3.make_pose(R, rng.uniform([-0.05, -0.05, 0.02], [0.05, 0.05, 0.15], (n, 3)))


def test_inverse_kinematics_reproduces_the_end_effector_exactly():
    for T in _ee_poses(50):
        q = robot.inverse_kinematics(T)
        assert abs(q[4]) < np.radians(80)  # far from the wrist's pitch singularity
        np.testing.assert_allclose(robot.forward_kinematics(q), T, atol=1e-12)
        chain = robot.T_WORLD_BASE.copy()  # the TF chain's edges compose to the same pose
        for _p, _c, T_pc in robot.arm_transforms(q):
            chain = chain @ T_pc
        for _p, _c, T_pc in robot.static_transforms()[1:]:
            chain = chain @ T_pc
        np.testing.assert_allclose(chain, T, atol=1e-12)


def test_urdf_forward_kinematics_matches_the_simulator(tmp_path):
    """yourdfpy on the written URDF (as mvtop reads a joint-states log) gives the simulator's
    end effector, fingers and tactile optical frames for the joint values it publishes."""
    path = tmp_path / "robot.urdf"
    path.write_text(robot.urdf_text(0.03))
    kin = UrdfKinematics(path)
    assert kin.root == robot.BASE_LINK
    assert kin.joints == set(robot.ARM_JOINTS + robot.FINGER_JOINTS)
    rng = np.random.default_rng(1)
    for T in _ee_poses(10, seed=2):
        left, right = rng.uniform(0.003, 0.02, 2)  # pad positions along ee y [m]
        q = list(robot.inverse_kinematics(T)) + robot.finger_joint_values(left, -right)
        links = kin.link_poses(list(robot.ARM_JOINTS + robot.FINGER_JOINTS), q)
        np.testing.assert_allclose(robot.T_WORLD_BASE @ links["ee"], T, atol=1e-12)
        for side, y in (("left", left), ("right", -right)):
            T_ee_finger = grip.finger_poses(2 * abs(y))[side]
            np.testing.assert_allclose(links[f"finger_{side}"], links["ee"] @ T_ee_finger, atol=1e-12)
            np.testing.assert_allclose(links[f"tactile_{side}_optical"],
                                       links["ee"] @ T_ee_finger @ grip.T_finger_tactile_optical(0.03), atol=1e-12)


def test_default_timing_is_every_sensor_at_every_nominal_time():
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    sched = capture_schedule(STAMPS[:5], SENSORS, SensorTiming(), rng)
    assert sched == [{name: t for name, _ in SENSORS} for t in STAMPS[:5]]
    assert rng.bit_generator.state == state  # draws nothing: default logs keep their bytes


def test_timing_rates_drops_and_jitter():
    timing = SensorTiming(camera_every=2, drop_fraction=0.25, jitter_s=0.008)
    sched = capture_schedule(STAMPS, SENSORS, timing, np.random.default_rng(5))
    assert sched == capture_schedule(STAMPS, SENSORS, timing, np.random.default_rng(5))  # seeded
    assert sched != capture_schedule(STAMPS, SENSORS, timing, np.random.default_rng(6))
    for k, (t, frame) in enumerate(zip(STAMPS, sched)):
        if k % 2:
            assert frame["front"] is None and frame["side"] is None
        for when in frame.values():
            assert when is None or abs(when - t) <= 8_000_000
    tactile = [f[s] for f in sched for s in ("left", "right")]
    cameras = [f[s] for f in sched[::2] for s in ("front", "side")]
    for kept in (tactile, cameras):
        lost = np.mean([w is None for w in kept])
        assert 0.19 < lost < 0.31, lost
    offsets = np.array([w - t for t, f in zip(STAMPS, sched) for w in f.values() if w is not None])
    assert offsets.std() > 3e6 and abs(offsets.mean()) < 1e6  # uniform over +-8 ms: std 4.6 ms


def test_timing_rejects_bad_values():
    with pytest.raises(ValueError, match="overlaps neighbouring frames"):
        capture_schedule(STAMPS[:3], SENSORS, SensorTiming(jitter_s=0.05), np.random.default_rng(0))
    for bad in (dict(camera_every=0), dict(drop_fraction=1.0), dict(jitter_s=-0.001), dict(jitter_s=float("nan"))):
        with pytest.raises(ValueError):
            SensorTiming(**bad)


def test_state_between_frames_is_the_interpolated_motion():
    T0, T1 = _ee_poses(2, seed=3)
    obj = se3.make_pose(np.eye(3), [0.0, 0.0, 0.02])
    a = EpisodeState(0, T0, obj, 0.010, -0.010, False, 0.003, 0.1)
    b = EpisodeState(100, T1, obj @ se3.make_pose(np.eye(3), [0.001, 0.0, 0.0]), 0.012, -0.012, True, 0.0, 5.0)
    assert state_at([a, b], 0) is a and state_at([a, b], 100) is b
    assert state_at([a, b], -5) is a and state_at([a, b], 150) is b
    mid = state_at([a, b], 25)
    np.testing.assert_allclose(mid.T_world_ee, se3.interpolate(T0, T1, 0.25), atol=1e-15)
    np.testing.assert_allclose(
        mid.T_world_object, se3.interpolate(a.T_world_object, b.T_world_object, 0.25), atol=1e-15
    )
    assert mid.pad_left_y_m == pytest.approx(0.0105) and mid.pad_right_y_m == pytest.approx(-0.0105)
    assert (mid.contact, mid.press_force_n) == (False, 0.1)


def test_scene_config_follows_the_recording_options():
    plain = scene_config("cube")
    assert plain == scene_config("cube", options=SimulateOptions())
    assert "robot" not in plain
    raw = scene_config("cube", options=SimulateOptions(image_format="raw", tactile_format="raw"))
    topics = [s["image_topic"] for s in raw["sensors"]["cameras"] + raw["sensors"]["tactile"]]
    assert topics == ["/cameras/front/image", "/cameras/side/image", "/tactile/left/image", "/tactile/right/image"]
    js = scene_config("cube", options=SimulateOptions(kinematics="joint-states", gel_distance_m=0.03))
    assert js["robot"] == {"urdf": URDF_FILE}
    assert all(t["gel_distance_m"] == 0.03 for t in js["sensors"]["tactile"])
    # the simulated depth topics are exact: every scene config rules out poses pressed deeper
    # than measured by 0.05 mm, the recorded masks' configs as well
    assert plain["masking"] == {"tactile_depth_tolerance_m": 5e-5}
    assert all(t["depth_topic"] == f"/tactile/{t['name']}/depth" for t in plain["sensors"]["tactile"])
    masked = scene_config("cube", options=SimulateOptions(mask_topics=True))
    assert masked["masking"] == {"tactile_depth_tolerance_m": 5e-5, "camera": {"backend": "topic"}}


def _frames(log: Path, cfg_path: Path):
    cfg = load_config(cfg_path)
    with McapLog(log) as mlog:
        reader = FrameReader(mlog, sensor_topics(cfg), log_topics(cfg))
        return list(reader), reader.skipped


@pytest.fixture(scope="module")
def small_logs(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    """Four-frame plug episodes at 160 x 120 px, the same seed, three kinematics."""
    out = {}
    for kin in ("ee-tf", "tf-chain", "joint-states"):
        d = tmp_path_factory.mktemp(kin)
        opts = SimulateOptions(episode=EpisodeOptions(frames=4), width=160, height=120, kinematics=kin)
        simulate("plug", 4, d / "plug.mcap", opts)
        out[kin] = (d / "plug.mcap", write_scene_config("plug", d / "plug.yaml", opts))
    return out


@pytest.mark.parametrize("kin", ["tf-chain", "joint-states"])
def test_robot_kinematics_logs_read_back_to_the_plain_frames(small_logs, kin):
    """The same episode recorded through the robot's TF chain, or through joint states and the
    URDF, reads back to the frames of the one-transform log: same images, and end effector,
    sensor poses and ground truth to rounding."""
    ref, _ = _frames(*small_logs["ee-tf"])
    frames, skipped = _frames(*small_logs[kin])
    assert len(frames) == len(ref) == 4 and not skipped
    for f, g in zip(frames, ref):
        assert f.stamp_ns == g.stamp_ns and f.contact == g.contact
        np.testing.assert_allclose(f.T_world_ee, g.T_world_ee, atol=1e-12)
        np.testing.assert_allclose(f.T_world_object_gt, g.T_world_object_gt, atol=1e-12)
        assert f.finger_opening_m == pytest.approx(g.finger_opening_m, abs=1e-12)
        for name in ("front", "side", "left", "right"):
            a = f.cameras.get(name) or f.tactile[name]
            b = g.cameras.get(name) or g.tactile[name]
            np.testing.assert_allclose(a.T_world_sensor, b.T_world_sensor, atol=1e-12)
            assert np.array_equal(a.image, b.image)
    with McapLog(small_logs[kin][0]) as mlog:
        summary = mlog.summary()
        assert summary.has_topic("/tf") == (kin == "tf-chain")
        js = next(mlog.messages("/joint_states")).msg
        assert list(js.name) == list(robot.ARM_JOINTS + robot.FINGER_JOINTS)


def test_cli_simulate_writes_a_joint_states_log_with_its_urdf(tmp_path):
    res = CliRunner().invoke(cli, [
        "simulate", "--object", "conn2", "--frames", "4", "--resolution", "160x120", "--kinematics", "joint-states",
        "--camera-every", "2", "--out", str(tmp_path / "c.mcap"), "--write-config", str(tmp_path / "c.yaml"),
    ])
    assert res.exit_code == 0, res.output
    cfg = load_config(tmp_path / "c.yaml")
    assert cfg.robot.urdf == tmp_path / URDF_FILE and cfg.robot.urdf.is_file()
    frames, skipped = _frames(tmp_path / "c.mcap", tmp_path / "c.yaml")
    assert [sorted(f.cameras) for f in frames] == [["front", "side"], [], ["front", "side"], []]
    assert all(sorted(f.tactile) == ["left", "right"] for f in frames) and not skipped
    # inspect counts the URDF's links as frames and does not ask for /tf (the log has none)
    res = CliRunner().invoke(cli, ["inspect", str(tmp_path / "c.mcap"), "--config", str(tmp_path / "c.yaml")])
    assert res.exit_code == 0, res.output
    assert "OK: every required topic and TF frame is present." in res.output
    assert "URDF links:" in res.output and "tactile_left_optical" in res.output
    assert not any(line.startswith("/tf ") for line in res.output.splitlines())
    # a frame neither in TF nor in the URDF is still reported
    text = (tmp_path / "c.yaml").read_text()
    assert "\nframes:" not in text
    (tmp_path / "d.yaml").write_text(text + "frames: {world: world, ee: tool_tip}\n")
    res = CliRunner().invoke(cli, ["inspect", str(tmp_path / "c.mcap"), "--config", str(tmp_path / "d.yaml")])
    assert res.exit_code != 0 and "missing TF frames: tool_tip" in res.output, res.output
    help_text = CliRunner().invoke(cli, ["simulate", "--help"]).output
    for option in ("--image-format", "--distortion", "--kinematics", "--camera-every", "--drop-fraction",
                   "--stamp-jitter-ms"):
        assert option in help_text
