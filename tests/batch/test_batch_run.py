"""A batch estimate on local worker processes: a bad log is a failed row and stops nothing, a
killed worker's job is run again from its checkpoint, every log's outputs equal a serial
single-log run, a re-run skips the finished logs, and the command line's summary and exit code."""

from __future__ import annotations

import csv
import json
import multiprocessing
import operator
import subprocess
import sys

from _batch_logs import CONFIG, assert_same_outputs, kill_worker_after, make_logs, serial_run

from mvtop_cli.batch.engine import LocalEngine, _child
from mvtop_cli.batch.run import RECORDS_DIR, TABLE_COLUMNS, BatchProgress, format_progress, run_batch


def test_local_batch_with_a_bad_log_and_a_killed_worker_equals_the_serial_runs(tmp_path):
    jobs = make_logs(tmp_path)
    out = tmp_path / "out"
    killed = kill_worker_after(out / "a", frames=2)
    seen: list[BatchProgress] = []
    summary = run_batch(jobs, out, LocalEngine(workers=2), progress=seen.append)
    killed["thread"].join(timeout=5)
    assert "pid" in killed, "the worker of log a was not killed before it finished"

    assert (summary["logs"], summary["ok"], summary["failed"], summary["skipped"]) == (3, 2, 1, 0)
    rows = {r["name"]: r for r in csv.DictReader((out / "runs.csv").open())}
    assert list(next(csv.reader((out / "runs.csv").open()))) == list(TABLE_COLUMNS)
    assert sorted(rows) == ["a", "b", "bad"]
    assert rows["bad"]["status"] == "failed"
    assert rows["bad"]["error"].startswith(f"{tmp_path / 'logs' / 'bad.mcap'}: truncated MCAP file (100000 bytes")
    assert not (out / "bad").exists()  # no partial output of a failed log
    for name in ("a", "b"):
        assert rows[name]["status"] == "ok" and rows[name]["frames"] == "6" and rows[name]["error"] == ""
        assert float(rows[name]["gt_translation_error_mm"]) < 5.0
    # the killed job ran twice and resumed from the frames its first run had checkpointed
    assert rows["a"]["starts"] == "2" and rows["b"]["starts"] == "1"
    assert int(rows["a"]["resumed_at_frame"]) >= killed["frames"] >= 2
    for job in jobs[:2]:
        assert_same_outputs(out / job.name, serial_run(job, tmp_path / "serial"))

    assert seen[0].done == 0 and seen[-1].done == 3 and seen[-1].failed == 1
    assert [p.done for p in seen] == [0, 1, 2, 3]
    assert format_progress(seen[-1]).startswith("estimate: 3/3 logs (1 failed), ")

    again = run_batch(jobs, out, LocalEngine(workers=2))  # the same command again: only the failed log runs
    assert (again["ok"], again["failed"], again["skipped"], again["ran"]) == (2, 1, 2, 1)
    starts = {p.stem: len(p.read_text().splitlines()) for p in (out / RECORDS_DIR).glob("*.starts")}
    assert starts == {"a": 2, "b": 1, "bad": 2}


def test_command_line_batch_summary_and_exit_code(tmp_path):
    jobs = make_logs(tmp_path)
    manifest = tmp_path / "runs.yaml"
    manifest.write_text("- {log: logs/a.mcap, seed: 4}\n- {log: logs/bad.mcap, name: broken}\n")
    args = ["--config", str(CONFIG), "--out", str(tmp_path / "out"), "--particles", "30", "--max-frames", "2"]
    proc = subprocess.run([sys.executable, "-m", "mvtop_cli", "estimate", "--manifest", str(manifest), *args],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout.startswith(f"estimated 2 logs into {tmp_path / 'out'} with 1 local worker in ")
    assert ": 1 ok, 1 failed, 0 finished before; median error vs ground truth " in proc.stdout
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert err[0].startswith(f"estimate: broken failed: {jobs[2].log}: truncated MCAP file")
    assert err[-1] == f"mvtop: error: 1 of 2 logs failed (see {tmp_path / 'out' / 'runs.csv'})"
    record = json.loads((tmp_path / "out" / RECORDS_DIR / "a.json").read_text())
    assert record["status"] == "ok" and record["command"].startswith(f"mvtop estimate {jobs[0].log} --config ")
    assert record["command"].endswith("--particles 30 --seed 4 --max-frames 2")

    bad = subprocess.run([sys.executable, "-m", "mvtop_cli", "estimate", str(tmp_path / "logs"), "--manifest",
                          str(manifest), *args], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.strip() == "mvtop: error: give either LOG arguments or --manifest, not both"


def test_a_worker_whose_parent_is_gone_ends_quietly(capfd):
    # a stopped batch or benchmark closes its end of each worker's pipe; a worker that finishes its
    # job after that has nobody to tell, and ends without a traceback
    recv, send = multiprocessing.Pipe(duplex=False)
    recv.close()
    _child(send, operator.add, 1, (1, 2))
    assert send.closed
    assert capfd.readouterr().err == ""
