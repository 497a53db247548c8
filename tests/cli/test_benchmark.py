"""`mvtop benchmark speed` and `mvtop benchmark accuracy` print real figures, resume, and stop cleanly."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from mvtop_cli.benchmarks.accuracy import read_results
from mvtop_cli.config import SearchConfig


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


def test_benchmark_speed_on_a_log_times_every_stage():
    root = Path(__file__).resolve().parents[2]
    # a rival check on the second frame (its search runs after the filter; beside the mode check, which
    # otherwise takes its place there): every stage is timed apart
    proc = run("benchmark", "speed", "--config", str(root / "configs" / "conn2.yaml"), "--log",
               str(root / "sample_logs" / "conn2.mcap"), "--max-frames", "3", "--set", "search.rival_every=2",
               "--set", "search.rival_beside_mode_check=true", "--json")
    assert proc.returncode == 0, proc.stderr
    prof = json.loads(proc.stdout)
    assert prof["frames_processed"] == 3 and prof["frames"] == 3
    assert prof["log_s"] == 0.2 and prof["startup_s"] > 0 and prof["wall_over_log"] > 0
    assert prof["tracked_frames"] == 0  # the tracking mode (filter.tracking_particles) is off by default
    stages = ("masking_s", "search_s", "filter_s", "checks_s", "diagnostics_s")
    for part in (prof["first_frame"], prof["later_frames_mean"]):
        assert all(part[k] > 0 for k in ("read_s", *stages, "likelihood_s", "step_s")), part
        # the five stages make up the step (each rounded to a microsecond), and every likelihood call is in it
        assert abs(sum(part[k] for k in stages) - part["step_s"]) <= 5e-6, part
        assert part["likelihood_s"] <= part["step_s"]
        assert part["poses_scored"] >= 500 and part["likelihood_calls"] >= 1
    # a search of the grasp prior scores M = 500 x init_factor poses, then M less its elite tenth a round: the
    # first frame runs one of search.first_frame_rounds (3,000 + 10 x 2,700), the rival check one of search.rounds
    # (3,000 + 12 x 2,700) on one of the two later frames
    s = SearchConfig()
    population = 500 * s.init_factor
    first_search, rival_search = (population + rounds * (population - round(s.elite_fraction * population))
                                  for rounds in (s.first_frame_rounds, s.rounds))
    assert first_search < prof["first_frame"]["poses_scored"] < 2 * first_search
    assert prof["later_frames_mean"]["poses_scored"] > rival_search / 2
    # the rival check's search is timed with the checks, not with the filter's re-search (1,850 poses a frame)
    assert prof["later_frames_mean"]["checks_s"] > prof["later_frames_mean"]["search_s"]
    assert set(prof["masking_ms_per_frame"]) >= {"camera_proposals_ms", "tactile_ms"}


def test_benchmark_speed_set_needs_a_log():
    proc = run("benchmark", "speed", "--set", "search.rival_every=0")
    assert proc.returncode != 0
    assert "--set needs --log" in proc.stderr


def test_benchmark_accuracy_runs_evaluates_and_resumes(tmp_path):
    out = tmp_path / "bench"
    args = ("benchmark", "accuracy", "--out", str(out), "--objects", "conn2", "--poses", "1", "--methods", "M-TOP",
            "--frames", "8", "--particles", "60")
    first = run(*args)
    assert first.returncode == 0, first.stderr
    result = out / "runs" / "conn2_1000_M-TOP" / "result.json"
    report = json.loads(result.read_text())
    summary = json.loads((out / "summary.json").read_text())
    agg = summary["table"]["M-TOP"]["conn2"]
    assert agg["runs"] == 1
    assert abs(agg["pose_error_mm"]["median"] - report["final"]["pose_error_mm"]) < 1e-9
    assert f"| M-TOP | {agg['pose_error_mm']['median']:.2f} /" in first.stdout
    # the part touches the receptacle at frame 7: the frame before it is scored and kept in the results
    before = report["before_contact"]
    assert before["contact_frame"] == 7 and before["frame"] == 6
    assert before["insertion_error_mm"] == report["per_frame"][6]["insertion_error_mm"]
    assert agg["before_contact_runs"] == 1 and agg["before_contact_success_rate"] == float(before["insertable"])
    rate = f"| M-TOP | {100 * float(before['insertable']):.0f} | {100 * float(before['insertable']):.0f} |"
    assert rate in first.stdout.split("just before contact")[1]
    assert read_results(out / "results.jsonl.gz")[0]["before_contact"] == before
    # each run keeps the warnings it raised, and the summary says how the suspect_estimate warning fell
    run_summary = json.loads((out / "runs" / "conn2_1000_M-TOP" / "summary.json").read_text())
    assert report["benchmark"]["warning_counts"] == run_summary["warning_counts"]
    # and why it is suspect or not, so another threshold can be judged from the finished runs
    assert report["benchmark"]["suspect"] == run_summary["suspect"]
    assert report["benchmark"]["suspect"]["raised"] == ("suspect_estimate" in run_summary["warning_counts"])
    assert summary["suspect"]["M-TOP"]["runs"] == 1
    # and the spread it reported at the end, to judge a warning on the covariance from the results alone
    assert report["benchmark"]["reported_std"] == {"translation_mm": 1e3 * run_summary["final"]["translation_std_m"],
                                                   "rotation_deg": run_summary["final"]["rotation_std_deg"]}
    assert read_results(out / "results.jsonl.gz")[0]["benchmark"]["reported_std"] == report["benchmark"]["reported_std"]
    assert "- M-TOP: far off " in first.stdout
    stamp = result.stat().st_mtime_ns
    again = run(*args)
    assert again.returncode == 0, again.stderr
    assert result.stat().st_mtime_ns == stamp  # resumed: the finished run was not redone
    assert (out / "summary.md").read_text() in again.stdout


def test_benchmark_accuracy_first_seed_picks_the_grasps(tmp_path):
    """--first-seed N runs grasps N, N+1, ...: the runs are named and simulated by those seeds."""
    out = tmp_path / "bench"
    proc = run("benchmark", "accuracy", "--out", str(out), "--objects", "conn2", "--poses", "2", "--first-seed", "5000",
               "--methods", "M-TOP", "--frames", "4", "--particles", "40")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["conn2_5000_M-TOP", "conn2_5001_M-TOP"]
    seeds = [json.loads((out / "runs" / f"conn2_{s}_M-TOP" / "result.json").read_text())["benchmark"]["seed"]
             for s in (5000, 5001)]
    assert seeds == [5000, 5001]


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


def test_benchmark_accuracy_results_carry_over_to_another_folder(tmp_path):
    """results.jsonl.gz of one folder, given to another with --import-results, counts as done
    there: only the missing run is made, and the tables cover both."""
    import gzip

    small = ("--objects", "conn2", "--methods", "M-TOP", "--frames", "6", "--particles", "60")
    a, b = tmp_path / "a", tmp_path / "b"
    first = run("benchmark", "accuracy", "--out", str(a), "--poses", "1", *small)
    assert first.returncode == 0, first.stderr
    records = [json.loads(line) for line in gzip.decompress((a / "results.jsonl.gz").read_bytes()).splitlines()]
    done = json.loads((a / "runs" / "conn2_1000_M-TOP" / "result.json").read_text())
    assert len(records) == 1 and records[0]["final"] == done["final"] and "per_frame" not in records[0]
    assert records[0]["trace"]["insertion_error_mm"] == [round(f["insertion_error_mm"], 4) for f in done["per_frame"]]
    assert len(records[0]["trace"]["rotation_error_deg"]) == 6
    code = records[0]["benchmark"]["code"]
    assert len(code) == 12 and records[0]["benchmark"]["simulate_seconds"] > 0

    second = run("benchmark", "accuracy", "--out", str(b), "--poses", "2", *small,
                 "--import-results", str(a / "results.jsonl.gz"))
    assert second.returncode == 0, second.stderr
    imported = json.loads((b / "runs" / "conn2_1000_M-TOP" / "result.json").read_text())
    assert imported["final"] == done["final"] and imported["imported_from"] == str(a / "results.jsonl.gz")
    assert not (b / "scenes" / "conn2_1000").exists()  # not simulated again
    made = json.loads((b / "runs" / "conn2_1001_M-TOP" / "result.json").read_text())
    summary = json.loads((b / "summary.json").read_text())
    assert summary["runs"] == summary["runs_requested"] == 2 and summary["imported_this_run"] == 1
    errors = sorted([done["final"]["pose_error_mm"], made["final"]["pose_error_mm"]])
    assert abs(summary["table"]["M-TOP"]["conn2"]["pose_error_mm"]["median"] - sum(errors) / 2) < 1e-12
    assert summary["totals"]["code_versions"] == {code: 2}
    assert f"2 of 2 runs (2 grasps per object x 1 objects x 1 methods); code {code} (2 runs)." in second.stdout
    # invocations are logged; the results file is the same bytes when nothing changed
    packed = (b / "results.jsonl.gz").read_bytes()
    again = run("benchmark", "accuracy", "--out", str(b), "--poses", "2", *small)
    assert again.returncode == 0, again.stderr
    assert (b / "results.jsonl.gz").read_bytes() == packed
    lines = [json.loads(x) for x in (b / "invocations.jsonl").read_text().splitlines()]
    assert [x["runs_made"] for x in lines] == [1, 0] and [x["runs_imported"] for x in lines] == [1, 0]
    assert json.loads((b / "summary.json").read_text())["totals"]["invocations"] == 2
    # --summary-only makes no run: the tables cover what is there, and say it is not complete
    c = tmp_path / "c"
    only = run("benchmark", "accuracy", "--out", str(c), "--poses", "3", *small, "--summary-only",
               "--import-results", str(b / "results.jsonl.gz"))
    assert only.returncode == 0, only.stderr
    assert "2 of 3 runs (3 grasps per object x 1 objects x 1 methods): not complete" in only.stdout
    assert not (c / "runs" / "conn2_1002_M-TOP").exists() and not (c / "scenes").exists()
    empty = run("benchmark", "accuracy", "--out", str(tmp_path / "d"), "--poses", "1", *small, "--summary-only")
    assert empty.returncode != 0 and "no finished run" in empty.stderr and "\n" not in empty.stderr.strip()


def test_benchmark_accuracy_refuses_a_damaged_results_file(tmp_path):
    import gzip

    bad = tmp_path / "results.jsonl.gz"
    bad.write_bytes(gzip.compress(b'{"benchmark": {"object": "conn2", "seed": 1000, "method": "M-TOP"}, '
                                  b'"final": {"insertable": true, "translation_error_mm": 0.1}}\n{"final": 3}\n'))
    proc = run("benchmark", "accuracy", "--out", str(tmp_path / "b"), "--objects", "conn2", "--poses", "1",
               "--methods", "M-TOP", "--import-results", str(bad))
    assert proc.returncode != 0
    assert f"{bad} line 2: expected a benchmark record" in proc.stderr
    assert not list((tmp_path / "b").glob("runs/*/result.json"))


def test_readme_benchmark_tables_are_those_of_the_committed_results(tmp_path):
    """The README's benchmark tables are what --summary-only prints over the committed results
    files it names (the current estimator's and the first one's), line for line (docs and data
    cannot drift apart)."""
    root = Path(__file__).resolve().parents[2]
    text = (root / "README.md").read_text()
    # each command the README gives, run as it is given (only the output folder differs)
    commands = re.findall(r"mvtop benchmark accuracy --out /tmp/bench (--poses \d+) --summary-only "
                          r"--import-results (benchmarks/accuracy/[\w./-]*results\.jsonl\.gz)", text)
    assert {path for _, path in commands} == {"benchmarks/accuracy/current-seeds-1000-1099/results.jsonl.gz",
                                              "benchmarks/accuracy/results.jsonl.gz"}, commands
    readme = text.splitlines()
    for k, (poses, path) in enumerate(commands):
        out = tmp_path / f"b{k}"
        proc = run("benchmark", "accuracy", "--out", str(out), *poses.split(), "--summary-only",
                   "--import-results", str(root / path))
        assert proc.returncode == 0, proc.stderr
        summary = (out / "summary.md").read_text().splitlines()
        rows = [line for line in summary if line.startswith("| M-")]
        assert len(rows) >= 9, path  # errors, success rates and times of three methods
        for line in [summary[0], *rows]:
            assert line in readme, f"{path}: {line}"


def test_benchmark_accuracy_set_changes_the_config_of_every_run_and_binds_the_folder(tmp_path):
    """--set KEY=VALUE reaches the estimator's config (the run's config.resolved.yaml), is
    recorded with the run and named in the tables; the folder then refuses other settings."""
    import yaml

    out = tmp_path / "bench"
    small = ("benchmark", "accuracy", "--out", str(out), "--objects", "conn2", "--poses", "1", "--methods", "M-TOP",
             "--frames", "4", "--particles", "30")
    proc = run(*small, "--set", "contact.softness_m=1e-4", "--set", "filter.temperature=0.01")
    assert proc.returncode == 0, proc.stderr
    run_dir = out / "runs" / "conn2_1000_M-TOP"
    resolved = yaml.safe_load((run_dir / "config.resolved.yaml").read_text())
    assert resolved["contact"]["softness_m"] == 1e-4 and resolved["filter"]["temperature"] == 0.01
    scene = yaml.safe_load((out / "scenes" / "conn2_1000" / "config.yaml").read_text())
    assert "softness_m" not in scene.get("contact", {})  # the scene config stays the simulator's own
    settings = {"contact.softness_m": 1e-4, "filter.temperature": 0.01}
    assert json.loads((run_dir / "result.json").read_text())["benchmark"]["settings"] == settings
    assert json.loads((out / "summary.json").read_text())["settings"] == settings
    assert "--set contact.softness_m=0.0001 --set filter.temperature=0.01)" in proc.stdout
    refused = run(*small)
    assert refused.returncode == 2
    assert refused.stderr.strip() == (f"mvtop: error: {out}: its runs were made with --set contact.softness_m=0.0001 "
                                      "--set filter.temperature=0.01, not no --set (one setting per benchmark folder: "
                                      "give another --out)")


def test_a_stopped_benchmark_stops_its_workers_and_says_how_to_go_on(tmp_path):
    out = tmp_path / "bench"
    proc = subprocess.Popen([sys.executable, "-m", "mvtop_cli", "benchmark", "accuracy", "--out", str(out),
                             "--objects", "conn2", "--poses", "2", "--methods", "M-TOP", "--frames", "30",
                             "--particles", "200", "--workers", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not all((out / "scenes" / f"conn2_{s}").is_dir() for s in (1000, 1001)):  # both workers started
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "Traceback" not in stderr, stderr
    assert stderr.splitlines()[-1] == (f"mvtop: benchmark accuracy interrupted (SIGTERM); the runs it finished are "
                                       f"kept in {out}: run the same command to go on")
    # the worker processes were stopped with it: nothing of the command's process group is left
    deadline = time.monotonic() + 30
    while True:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "worker processes outlived the stopped benchmark"
        time.sleep(0.2)
