"""TF buffer: chains of static and moving transforms, interpolation against known motion, errors."""

from __future__ import annotations

import numpy as np
import pytest
from _io_scene import MS, SEC, T0, Scene, pose, rot, write_scene

from mvtop_cli.errors import LogError
from mvtop_cli.geometry import se3
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.tf_buffer import PoseSeries, TfBuffer


def add_pose(buf: TfBuffer, parent: str, child: str, t: int, T: np.ndarray) -> None:
    buf.add_dynamic(parent, child, t, T[:3, 3], se3.to_quat_xyzw(T))


def line_motion(t_ns: int) -> np.ndarray:
    """ee moves along a known line at 0.1 m/s and turns about a fixed axis at 0.8 rad/s."""
    s = (t_ns - T0) / SEC
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    return se3.make_pose(
        se3.rotvec_to_matrix(axis * 0.8 * s), np.array([0.4, -0.1, 0.3]) + s * np.array([0.1, 0.0, -0.05])
    )


@pytest.fixture
def moving_ee() -> TfBuffer:
    buf = TfBuffer(source="test.mcap")
    for i in range(11):  # 10 Hz for 1 s
        t = T0 + i * 100 * MS
        add_pose(buf, "world", "ee", t, line_motion(t))
    buf.add_static("world", "cam_optical", pose(rot("x", np.pi), [0.0, 0.0, 1.0]))
    return buf


def test_interpolation_between_samples_is_exact_for_constant_velocity(moving_ee):
    for t in [T0, T0 + 37 * MS, T0 + 150 * MS, T0 + 555_555_555, T0 + SEC]:
        np.testing.assert_allclose(moving_ee.lookup("world", "ee", t), line_motion(t), atol=1e-12)


def test_static_and_dynamic_combine(moving_ee):
    t = T0 + 425 * MS
    T_world_cam = pose(rot("x", np.pi), [0.0, 0.0, 1.0])
    expected = se3.invert(T_world_cam) @ line_motion(t)
    np.testing.assert_allclose(moving_ee.lookup("cam_optical", "ee", t), expected, atol=1e-12)
    # static-only paths work at any time
    np.testing.assert_allclose(moving_ee.lookup("world", "cam_optical", -5), T_world_cam, atol=1e-15)
    assert moving_ee.time_bounds("world", "cam_optical") == (-np.inf, np.inf)
    assert moving_ee.time_bounds("cam_optical", "ee") == (T0, T0 + SEC)


def test_lookup_is_inverse_consistent(moving_ee):
    rng = np.random.default_rng(3)
    for t in rng.integers(T0, T0 + SEC, 5):
        a = moving_ee.lookup("ee", "cam_optical", int(t))
        b = moving_ee.lookup("cam_optical", "ee", int(t))
        np.testing.assert_allclose(a @ b, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(moving_ee.lookup("ee", "ee", int(t)), np.eye(4))


def test_time_outside_data_fails_unless_within_tolerance(moving_ee):
    with pytest.raises(
        LogError,
        match=r"test\.mcap: transform 'world' -> 'ee' is not available at t=1700000001000000001 ns "
        r"\(data covers 1700000000000000000\.\.1700000001000000000 ns, extrapolation tolerance 0 ns\)",
    ):
        moving_ee.lookup("world", "ee", T0 + SEC + 1)
    with pytest.raises(LogError, match="not available at t=1699999999999999999 ns"):
        moving_ee.lookup("cam_optical", "ee", T0 - 1)

    tolerant = TfBuffer(extrapolation_tolerance_ns=5 * MS, source="test.mcap")
    for i in range(3):
        add_pose(tolerant, "world", "ee", T0 + i * 100 * MS, line_motion(T0 + i * 100 * MS))
    # within tolerance the end pose is held
    np.testing.assert_allclose(tolerant.lookup("world", "ee", T0 + 204 * MS), line_motion(T0 + 200 * MS), atol=1e-12)
    np.testing.assert_allclose(tolerant.lookup("world", "ee", T0 - 5 * MS), line_motion(T0), atol=1e-12)
    with pytest.raises(LogError, match="extrapolation tolerance 5000000 ns"):
        tolerant.lookup("world", "ee", T0 + 206 * MS)


def test_unknown_and_disconnected_frames(moving_ee):
    with pytest.raises(
        LogError, match=r"test\.mcap: frame 'gripper' is not in the TF tree \(known frames: cam_optical, ee, world\)"
    ):
        moving_ee.lookup("world", "gripper", T0)
    moving_ee.add_static("table", "receptacle", np.eye(4))
    with pytest.raises(
        LogError,
        match=r"frames 'receptacle' and 'ee' are not connected in the TF tree \(their roots are 'table' and 'world'\)",
    ):
        moving_ee.lookup("receptacle", "ee", T0)


def test_tree_violations_are_reported():
    buf = TfBuffer(source="x.mcap")
    buf.add_static("world", "cam", np.eye(4))
    with pytest.raises(LogError, match=r"frame 'cam' has two parents, 'world' and 'base' \(expected a tree"):
        buf.add_static("base", "cam", np.eye(4))
    with pytest.raises(LogError, match=r"published both as static and as dynamic"):
        buf.add_dynamic("world", "cam", T0, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(LogError, match=r"invalid quaternion \[0\.0, 0\.0, 0\.0, 0\.0\]"):
        buf.add_dynamic("world", "ee", T0, [0, 0, 0], [0, 0, 0, 0])


def test_multi_link_chain_from_a_written_log(tmp_path):
    # world -> base (static) -> link (moving) -> ee (moving) -> tactile (static), through MCAP.
    path = tmp_path / "chain.mcap"
    sc: Scene = write_scene(path, "lz4", early_image=False)
    buf = TfBuffer(source=str(path))
    with McapLog(path) as log:
        for m in log.messages(["/tf_static", "/tf"]):
            buf.add_tf_message(m.msg, static=m.topic == "/tf_static")
    assert buf.frames == {
        "world", "base", "link", "ee", "tactile_left_optical", "tactile_right_optical", "front_optical", "side_optical"
    }
    assert buf.parent("ee") == "link" and buf.is_static("ee", "tactile_left_optical")
    rng = np.random.default_rng(7)
    for t in [T0, T0 + SEC, *map(int, rng.integers(T0, T0 + SEC, 20))]:
        np.testing.assert_allclose(buf.lookup("world", "ee", t), sc.T_world_ee(t), atol=1e-12)
        np.testing.assert_allclose(
            buf.lookup("front_optical", "tactile_left_optical", t),
            se3.invert(sc.T_world_front) @ sc.T_world_ee(t) @ sc.T_ee_left,
            atol=1e-12,
        )
        np.testing.assert_allclose(
            buf.lookup("tactile_right_optical", "base", t),
            se3.invert(sc.T_world_ee(t) @ sc.T_ee_right) @ sc.T_world_base,
            atol=1e-12,
        )


def test_edges_are_stored_as_numpy_series():
    buf = TfBuffer()
    for i in (2, 0, 1, 1):  # out of order, with a duplicate stamp (the later sample wins)
        add_pose(buf, "world", "ee", T0 + i, pose(np.eye(3), [i, 0, 0]))
    buf.add_dynamic("world", "ee", T0 + 1, [5.0, 0, 0], [0, 0, 0, 1])
    buf.lookup("world", "ee", T0)
    series = buf._edges["ee"].series
    assert isinstance(series, PoseSeries)
    assert series.stamps_ns.dtype == np.int64 and series.stamps_ns.tolist() == [T0, T0 + 1, T0 + 2]
    assert series.translations.shape == (3, 3) and series.quats_xyzw.shape == (3, 4)
    np.testing.assert_allclose(buf.lookup("world", "ee", T0 + 1)[:3, 3], [5.0, 0, 0])
