"""`mvtop benchmark speed` and `mvtop benchmark accuracy` print real figures and resume."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, timeout=900)


def test_benchmark_speed_json_rows():
    proc = run("benchmark", "speed", "--particles", "50,200", "--repeats", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)
    assert [r["particles"] for r in rows] == [50, 200]
    for r in rows:
        assert r["evals_per_s"] > 0 and r["reference_evals_per_s"] > 0
        assert r["evals_per_s"] > r["reference_evals_per_s"]  # batched beats one render per particle


def test_benchmark_accuracy_runs_evaluates_and_resumes(tmp_path):
    out = tmp_path / "bench"
    args = ("benchmark", "accuracy", "--out", str(out), "--objects", "conn2", "--poses", "1", "--methods", "M-TOP",
            "--frames", "6", "--particles", "60")
    first = run(*args)
    assert first.returncode == 0, first.stderr
    result = out / "runs" / "conn2_1000_M-TOP" / "result.json"
    report = json.loads(result.read_text())
    summary = json.loads((out / "summary.json").read_text())
    agg = summary["table"]["M-TOP"]["conn2"]
    assert agg["runs"] == 1
    assert abs(agg["pose_error_mm"]["median"] - report["final"]["pose_error_mm"]) < 1e-9
    assert f"| M-TOP | {agg['pose_error_mm']['median']:.2f} /" in first.stdout
    stamp = result.stat().st_mtime_ns
    again = run(*args)
    assert again.returncode == 0, again.stderr
    assert result.stat().st_mtime_ns == stamp  # resumed: the finished run was not redone
    assert (out / "summary.md").read_text() in again.stdout


def test_benchmark_accuracy_box_plots_one_box_per_object_and_method(tmp_path):
    import re

    import numpy as np

    out = tmp_path / "bench"
    objects, methods = ("conn2", "conn1"), ("M-TOP", "M-VOP")
    proc = run("benchmark", "accuracy", "--out", str(out), "--objects", ",".join(objects), "--poses", "2",
               "--methods", ",".join(methods), "--frames", "4", "--particles", "30")
    assert proc.returncode == 0, proc.stderr
    page = (out / "summary.html").read_text()
    svgs = re.findall(r"<svg .*?</svg>", page, flags=re.S)
    assert len(svgs) == 3  # bounding-box pose error, translation error, rotation error
    assert "log scale" in svgs[0] and "bounding-box" in svgs[0]
    for svg, key in zip(svgs, ("pose_error_mm", "translation_error_mm", "rotation_error_deg")):
        boxes = re.findall(r'<g class="box" data-group="([^"]+)" data-series="([^"]+)" data-n="(\d+)" '
                           r'data-median="([^"]+)">', svg)
        assert sorted((g, s) for g, s, _, _ in boxes) == sorted((o, m) for o in objects for m in methods)
        for obj, method, n, median in boxes:
            values = [json.loads((out / "runs" / f"{obj}_{seed}_{method}" / "result.json").read_text())["final"][key]
                      for seed in (1000, 1001)]
            assert int(n) == 2
            assert abs(float(median) - float(np.median(values))) < 1e-12
    assert "| method | conn2 | conn1 |" in proc.stdout and "Time per run" in proc.stdout
