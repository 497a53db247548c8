"""scripts/perturb_extrinsics.py: the copied log differs from the original only in the named
camera frame's static transform, turned by the given angle about its own axis."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

ROOT = Path(__file__).resolve().parents[2]


def _first_frame(log_path: Path):
    cfg = load_config(ROOT / "configs" / "conn2.yaml")
    with McapLog(log_path) as log:
        return next(iter(FrameReader(log, sensor_topics(cfg), log_topics(cfg))))


def test_the_named_camera_is_turned_and_nothing_else_changes(tmp_path: Path):
    src, out = ROOT / "sample_logs" / "conn2.mcap", tmp_path / "turned.mcap"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "perturb_extrinsics.py"), str(src), str(out),
                           "front_optical", "2", "--axis", "x"], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "front_optical turned 2 deg about its x axis" in done.stdout
    with McapLog(src) as a, McapLog(out) as b:
        assert {t.name: t.message_count for t in a.summary().topics} == \
               {t.name: t.message_count for t in b.summary().topics}
    before, after = _first_frame(src), _first_frame(out)
    T0, T1 = before.cameras["front"].T_world_sensor, after.cameras["front"].T_world_sensor
    turn = se3.invert(T0) @ T1  # the turn in the camera's own frame
    np.testing.assert_allclose(turn[:3, 3], 0.0, atol=1e-9)
    np.testing.assert_allclose(se3.matrix_to_rotvec(turn[:3, :3]), [np.radians(2.0), 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(after.cameras["side"].T_world_sensor, before.cameras["side"].T_world_sensor, atol=1e-12)
    np.testing.assert_array_equal(after.cameras["front"].image, before.cameras["front"].image)


def test_an_unknown_frame_is_one_error_line_and_no_output(tmp_path: Path):
    out = tmp_path / "turned.mcap"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "perturb_extrinsics.py"),
                           str(ROOT / "sample_logs" / "conn2.mcap"), str(out), "nope_optical", "1"],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode != 0
    assert "no /tf_static transform has child frame 'nope_optical'" in done.stderr
    assert not out.exists()


@pytest.fixture(autouse=True)
def _package_on_path(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
