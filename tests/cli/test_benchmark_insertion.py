"""`mvtop benchmark insertion` runs closed-loop grasps, tabulates them, keeps logs and resumes."""

from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.benchmarks.insertion import aggregate, read_results


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, timeout=900)


def test_benchmark_insertion_runs_tabulates_and_resumes(tmp_path):
    out = tmp_path / "bench"
    args = ("benchmark", "insertion", "--out", str(out), "--objects", "conn2", "--poses", "1", "--methods", "M-TOP",
            "--particles", "30", "--attempts", "2", "--keep-logs")
    first = run(*args)
    assert first.returncode == 0, first.stderr
    run_dir = out / "runs" / "conn2_1000_M-TOP"
    report = json.loads((run_dir / "result.json").read_text())
    ins = report["insertion"]
    assert report["benchmark"]["particles"] == 30 and report["benchmark"]["attempts_allowed"] == 2
    assert 1 <= ins["attempts"] <= 2 and len(ins["per_attempt"]) == ins["attempts"]
    assert ins["per_attempt"][-1]["last_frame"] == ins["frames"] - 1
    assert sorted(p.name for p in (run_dir / "logs").iterdir()) == [f"attempt_{i + 1}.mcap"
                                                                    for i in range(ins["attempts"])]
    rate = 100 if ins["success"] else 0
    assert f"| M-TOP | {rate} | {rate} |" in first.stdout
    assert (ins["time_to_insert_s"] == ins["frames"] / 10.0) if ins["success"] else ins["time_to_insert_s"] is None
    records = [json.loads(line) for line in gzip.decompress((out / "results.jsonl.gz").read_bytes()).splitlines()]
    assert records == [report]
    stamp = (run_dir / "result.json").stat().st_mtime_ns
    again = run(*args)
    assert again.returncode == 0, again.stderr
    assert (run_dir / "result.json").stat().st_mtime_ns == stamp  # resumed: the finished run was not redone
    assert (out / "summary.md").read_text() in again.stdout
    other = run("benchmark", "insertion", "--out", str(out), "--objects", "conn2", "--poses", "1", "--methods",
                "M-TOP", "--attempts", "3", "--summary-only")
    assert other.returncode != 0 and "made with --attempts 2, not 3" in other.stderr
    elsewhere = tmp_path / "elsewhere"  # the results file carries the runs to another folder
    moved = run("benchmark", "insertion", "--out", str(elsewhere), "--objects", "conn2", "--poses", "1", "--methods",
                "M-TOP", "--attempts", "2", "--summary-only", "--import-results", str(out / "results.jsonl.gz"))
    assert moved.returncode == 0, moved.stderr
    table = (out / "summary.md").read_text().split("\n", 1)[1]  # below the line naming the code versions
    assert table == (elsewhere / "summary.md").read_text().split("\n", 1)[1]
    assert (elsewhere / "results.jsonl.gz").read_bytes() != b""


def test_benchmark_insertion_rejects_an_unknown_method(tmp_path):
    proc = run("benchmark", "insertion", "--out", str(tmp_path / "b"), "--methods", "M-VTOP,CHSEL")
    assert proc.returncode != 0
    assert "--methods: unknown CHSEL (expected M-VTOP, M-VOP, M-TOP)" in proc.stderr
    assert not (tmp_path / "b").exists()


def test_benchmark_insertion_refuses_a_damaged_results_file(tmp_path):
    bad = tmp_path / "results.jsonl"
    bad.write_text('{"benchmark": {"object": "cube"}}\n')
    proc = run("benchmark", "insertion", "--out", str(tmp_path / "b"), "--summary-only", "--import-results", str(bad))
    assert proc.returncode != 0
    assert f"{bad} line 1: expected an insertion record (mvtop-insertion/1)" in proc.stderr


def test_benchmark_insertion_stops_on_an_unreachable_cluster_before_its_folder(tmp_path):
    """As ``estimate --ray`` (batch/engine.py): the address is checked before any output (port 9
    on this machine: nothing listens there)."""
    pytest.importorskip("ray")
    out = tmp_path / "b"
    proc = run("benchmark", "insertion", "--out", str(out), "--objects", "cube", "--poses", "1", "--ray", "127.0.0.1:9")
    assert proc.returncode == 2
    assert proc.stderr.startswith("mvtop: error: --ray 127.0.0.1:9: cannot reach a Ray cluster there (")
    assert not out.exists()


@pytest.mark.parametrize(("method", "folder"), [
    ("M-VTOP", "m-vtop-gel-depth-seeds-1000-1099"),
    ("M-VTOP, earlier estimator", "m-vtop-seeds-1000-1099"),
    ("M-VOP", "m-vop-seeds-1000-1099"),
    ("M-TOP", "m-top-seeds-1000-1099"),
])
def test_readme_insertion_rows_are_the_committed_results(method, folder):
    # The README's Table I rows over 100 grasps per object are the committed results, recounted
    # here (docs and data cannot drift apart).
    root = Path(__file__).resolve().parents[2]
    records = read_results(root / "benchmarks" / "insertion" / folder / "results.jsonl.gz")
    objects = ["cube", "shaft_peg", "plug", "conn1", "conn2"]
    per = {o: aggregate([r for r in records if r["benchmark"]["object"] == o]) for o in objects}
    assert all(per[o]["runs"] == 100 for o in objects)
    rates = [100 * per[o]["success_rate"] for o in objects]
    first = [100 * per[o]["first_attempt_rate"] for o in objects]
    readme = (root / "README.md").read_text().splitlines()
    row = f"| {method} | " + " | ".join(f"{v:.0f}" for v in rates) + f" | **{np.mean(rates):.1f}** |"
    assert row in readme, row
    row = f"| {method} success at the first attempt, % | " + " | ".join(f"{v:.0f}" for v in first) + \
        f" | {np.mean(first):.0f} |"
    assert row in readme, row
