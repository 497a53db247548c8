"""The shipped configs and sample logs match what the generator makes today."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mvtop_cli.config import load_config
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.inspect import inspect_log
from mvtop_cli.pipelines.simulate import scene_config
from mvtop_cli.sim.objects import list_objects

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", list_objects())
def test_config_is_current_and_valid(name):
    path = REPO / "configs" / f"{name}.yaml"
    assert yaml.safe_load(path.read_text()) == scene_config(name), f"{path} is stale: run scripts/make_samples.py"
    cfg = load_config(path)
    assert cfg.object.name == name
    assert cfg.object.clearance_m > 0


@pytest.mark.parametrize("name", list_objects())
def test_sample_log_pairs_with_its_config(name):
    log = REPO / "sample_logs" / f"{name}.mcap"
    cfg = load_config(REPO / "configs" / f"{name}.yaml")
    report = inspect_log(log, cfg.required_topics(), cfg.required_frames())
    assert report.ok, report
    summary = McapLog(log).summary()
    assert 20 <= summary.topic("/ground_truth/object_pose").message_count <= 40
    assert log.stat().st_size < 4_000_000


def test_sample_logs_fit_in_git():
    total = sum(p.stat().st_size for p in (REPO / "sample_logs").glob("*.mcap"))
    assert total < 30_000_000


def test_real_setup_template_loads_and_checks_a_log():
    cfg = load_config(REPO / "configs" / "template_realsense_gelsight.yaml")
    assert cfg.topics.ground_truth is None and cfg.masking.camera.backend == "classical"
    # the template's layout is the simulator's: the sample log satisfies it
    report = inspect_log(REPO / "sample_logs" / "conn1.mcap", cfg.required_topics(), cfg.required_frames())
    assert report.ok, report
