"""``mvtop benchmark insertion --scene``, ``--recorded-masks-px`` and ``--set``: the tables name
them, and a setting no scene config takes is refused (one of each per folder:
``test_folder_checks.py``)."""

from __future__ import annotations

import json

import pytest

from mvtop_cli.benchmarks.insertion import InsertionBenchmarkOptions, format_table, run_insertion_benchmark


def test_the_summary_names_a_hard_scene(tmp_path):
    run = tmp_path / "runs" / "cube_1000_M-TOP"
    run.mkdir(parents=True)
    per_attempt = [{"index": 1, "first_frame": 0, "last_frame": 14, "outcome": "inserted", "depth_mm": 20.3,
                    "align_error_mm": 0.05, "align_error_deg": 0.4}]
    report = {"schema": "mvtop-insertion/1",
              "benchmark": {"object": "cube", "seed": 1000, "method": "M-TOP", "attempts_allowed": 3, "scene": "hard",
                            "seconds": 60.0, "cpu_seconds": 100.0, "particles": 500, "code": "abc"},
              "insertion": {"success": True, "attempts": 1, "frames": 15, "rate_hz": 10.0, "time_to_insert_s": 1.5,
                            "compliance_mm": 0.2, "per_attempt": per_attempt}}
    (run / "result.json").write_text(json.dumps(report))
    options = InsertionBenchmarkOptions(objects=("cube",), poses=1, methods=("M-TOP",), scene="hard",
                                        summary_only=True)
    summary = run_insertion_benchmark(tmp_path, options)
    assert summary["scene"] == "hard" and summary["table"]["M-TOP"]["cube"]["success_rate"] == 1.0
    first = format_table(summary).splitlines()[0]
    assert first == ("1 of 1 runs (1 grasps per object x 1 objects x 1 methods, up to 3 attempts, hard scene); "
                     "code abc (1 runs).")
    assert (tmp_path / "summary.md").read_text() == format_table(summary)
    default = format_table({**summary, "scene": "default"}).splitlines()[0]
    assert default == "1 of 1 runs (1 grasps per object x 1 objects x 1 methods, up to 3 attempts); code abc (1 runs)."


def test_the_summary_names_recorded_masks():
    summary = {"objects": ["cube"], "poses": 1, "methods": ["M-VTOP"], "attempts": 3, "scene": "default",
               "recorded_masks_px": 1, "runs": 1, "runs_requested": 1, "totals": {"code_versions": {"abc": 1}},
               "table": {}}
    assert format_table(summary).splitlines()[0] == (
        "1 of 1 runs (1 grasps per object x 1 objects x 1 methods, up to 3 attempts, camera masks recorded by a "
        "simulated segmenter (outlines off by up to 1 px)); code abc (1 runs).")


def test_a_setting_no_scene_config_takes_is_refused_before_the_folder_exists(tmp_path):
    from mvtop_cli.errors import ConfigError

    options = InsertionBenchmarkOptions(objects=("cube",), poses=1, methods=("M-TOP",),
                                        settings={"contact.softnes_m": 5e-5})
    with pytest.raises(ConfigError) as info:
        run_insertion_benchmark(tmp_path / "out", options)
    assert str(info.value) == "--set: contact.softnes_m: unknown key (did you mean 'softness_m'?)"
    assert not (tmp_path / "out").exists()


def test_the_summary_names_the_settings():
    summary = {"objects": ["cube"], "poses": 1, "methods": ["M-VTOP"], "attempts": 3, "scene": "default",
               "settings": {"contact.softness_m": 5e-5, "masking.camera.backend": "grabcut"}, "runs": 1,
               "runs_requested": 1, "totals": {"code_versions": {"abc": 1}}, "table": {}}
    assert format_table(summary).splitlines()[0] == (
        "1 of 1 runs (1 grasps per object x 1 objects x 1 methods, up to 3 attempts, --set contact.softness_m=5e-05 "
        "--set masking.camera.backend=grabcut); code abc (1 runs).")
