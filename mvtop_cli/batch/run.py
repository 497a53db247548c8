"""A batch estimate: the job as a worker runs it, and the driver that hands out the jobs,
skips the finished ones, follows the progress and writes the results table.

Layout of the output folder ``OUT``:

- ``OUT/NAME/``: the log's outputs, those of ``mvtop estimate LOG --config CFG --out OUT/NAME``
  (track.mcap, track.csv, config.resolved.yaml byte for byte; summary.json the same up to its
  timings);
- ``OUT/.mvtop-batch/NAME.json``: the job's record, written by the worker when the job ends
  (``ok`` or ``failed`` with its one-line error), with a key of its inputs: a re-run skips the
  jobs whose record is ``ok`` with the same key and whose outputs are there;
- ``OUT/.mvtop-batch/NAME.starts``: one line per start of the job (host, process, time): a job
  restarted after its worker died shows two;
- ``OUT/runs.csv``: one row per record in ``OUT/.mvtop-batch``, i.e. every log any batch
  (from any machine) estimated into ``OUT``, rewritten at the end of each batch.

Workers read the logs and write ``OUT`` by their absolute paths: on a cluster, the logs and
``OUT`` must be on a file system every node mounts at the same place (NFS, a cluster file
system, an object store mounted with a FUSE driver).
"""

from __future__ import annotations

import csv
import io
import json
import os
import socket
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from urllib.parse import quote, unquote

import numpy as np

from ..durations import format_duration
from ..errors import MvtopError
from ..io.atomic import atomic_output
from .engine import LocalEngine, RayEngine
from .jobs import EstimateJob

RECORDS_DIR = ".mvtop-batch"
TABLE_FILE = "runs.csv"
TABLE_COLUMNS = (
    "name", "status", "frames", "frames_skipped", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw",
    "spread_translation_mm", "spread_rotation_deg", "warnings", "warning_kinds", "run_time_s", "job_time_s", "cpu_s",
    "gt_translation_error_mm", "gt_rotation_error_deg", "resumed_at_frame", "starts", "host", "log", "config", "error",
)


def record_path(records_dir: Path, name: str) -> Path:
    """The record file of job ``name`` (its name quoted: one flat folder whatever the name)."""
    return Path(records_dir) / f"{quote(name, safe='')}.json"


def _starts_path(records_dir: Path, name: str) -> Path:
    return Path(records_dir) / f"{quote(name, safe='')}.starts"


def one_line(err: BaseException) -> str:
    """An exception as one line: the project's errors by their message, others with their type."""
    text = " ".join(str(err).split())
    if isinstance(err, MvtopError):
        return text or type(err).__name__
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def run_estimate_job(job: EstimateJob, records_dir: str) -> dict:
    """Estimate one log into ``job.out`` and write its record; returns the record. Runs on a
    worker. An error of the job (a bad log, the estimator failing) is the record's ``error``,
    not an exception. A checkpoint left in ``job.out`` by a run that was stopped (a killed
    worker) is resumed: the outputs are those of an uninterrupted run."""
    from ..config import load_config
    from ..pipelines.checkpoint import frames_done
    from ..pipelines.estimate import EstimateOptions, estimate

    t0, c0 = time.perf_counter(), time.process_time()
    records = Path(records_dir)
    records.mkdir(parents=True, exist_ok=True)
    host = socket.gethostname()
    with _starts_path(records, job.name).open("a") as fh:
        fh.write(f"{host} {os.getpid()} {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n")
    record = {"name": job.name, "log": job.log, "config": job.config, "out": job.out, "key": job.key(),
              "command": job.command_line(), "host": host}
    try:
        cfg = load_config(job.config)
        options = EstimateOptions(modalities=job.modalities, num_particles=job.particles, seed=job.seed,
                                  max_frames=job.max_frames)
        out = Path(job.out)
        resume = frames_done(out) > 0
        try:
            summary = estimate(Path(job.log), cfg, out, options, resume=resume)
        except MvtopError:
            if not resume:
                raise
            summary = estimate(Path(job.log), cfg, out, options)  # a checkpoint of other inputs: start over
        record.update(status="ok", **_summary_fields(summary))
    except Exception as err:
        record.update(status="failed", error=one_line(err), traceback=traceback.format_exc(limit=8))
    record["job_time_s"] = round(time.perf_counter() - t0, 3)
    record["cpu_s"] = round(time.process_time() - c0, 3)  # all threads of the worker process
    record["starts"] = _count_lines(_starts_path(records, job.name))
    write_record(records, record)
    return record


def _summary_fields(summary: dict) -> dict:
    f = summary["final"]
    t, q = f["T_world_object"]["translation_m"], f["T_world_object"]["quaternion_xyzw"]
    counts = summary.get("warning_counts", {})
    out = {
        "frames": summary["frames_processed"], "frames_skipped": summary["frames_skipped"],
        "x_m": t[0], "y_m": t[1], "z_m": t[2], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3],
        "spread_translation_mm": 1000.0 * f["translation_std_m"], "spread_rotation_deg": f["rotation_std_deg"],
        "warnings": int(sum(counts.values())), "warning_kinds": "|".join(sorted(counts)),
        "run_time_s": summary["run_time_s"], "resumed_at_frame": summary.get("resumed_at_frame", 0),
    }
    if "ground_truth_translation_error_mm" in f:
        out["gt_translation_error_mm"] = f["ground_truth_translation_error_mm"]
        out["gt_rotation_error_deg"] = f["ground_truth_rotation_error_deg"]
    return out


def _count_lines(path: Path) -> int:
    try:
        return len(path.read_text().splitlines())
    except OSError:
        return 0


def write_record(records_dir: Path, record: dict) -> None:
    with atomic_output(record_path(records_dir, record["name"]), "w") as fh:
        json.dump(record, fh, indent=1, sort_keys=True)
        fh.write("\n")


def read_records(records_dir: Path) -> dict[str, dict]:
    """Every job record in ``records_dir`` by job name (an unreadable one is left out: its job
    counts as not done)."""
    out: dict[str, dict] = {}
    if not Path(records_dir).is_dir():
        return out
    for p in sorted(Path(records_dir).glob("*.json")):
        try:
            rec = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(rec, dict) and rec.get("name") == unquote(p.stem):
            out[rec["name"]] = rec
    return out


def is_finished(job: EstimateJob, record: dict | None) -> bool:
    """Whether a re-run may skip ``job``: an ``ok`` record with the job's key, outputs present."""
    return (record is not None and record.get("status") == "ok" and record.get("key") == job.key()
            and (Path(job.out) / "summary.json").is_file())


def table_text(records: list[dict]) -> str:
    """runs.csv: TABLE_COLUMNS, one row per record, in name order."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(TABLE_COLUMNS)
    for rec in sorted(records, key=lambda r: r["name"]):
        row = []
        for col in TABLE_COLUMNS:
            v = rec.get(col)
            row.append("" if v is None else f"{v:.9g}" if isinstance(v, float) else str(v))
        w.writerow(row)
    return buf.getvalue()


def write_table(out_root: Path) -> Path:
    path = Path(out_root) / TABLE_FILE
    with atomic_output(path, "w") as fh:
        fh.write(table_text(list(read_records(Path(out_root) / RECORDS_DIR).values())))
    return path


@dataclass(frozen=True)
class BatchProgress:
    """The batch so far: jobs ``done`` of ``total`` (``skipped`` as finished before, ``failed``
    among the done), seconds elapsed in this run and the estimated seconds left (None until a
    job of this run ended); ``last``: the record of the job that just ended."""

    done: int
    failed: int
    skipped: int
    total: int
    elapsed_s: float
    left_s: float | None
    last: dict | None = None


def format_progress(p: BatchProgress, label: str = "estimate") -> str:
    """One progress line for logs: ``estimate: 4/10 logs (1 failed), 1 min 3 s elapsed, about 2 min left``."""
    failed = f" ({p.failed} failed)" if p.failed else ""
    left = f", about {format_duration(p.left_s)} left" if p.left_s is not None and p.done < p.total else ""
    return f"{label}: {p.done}/{p.total} logs{failed}, {format_duration(p.elapsed_s)} elapsed{left}"


def run_batch(jobs: list[EstimateJob], out_root: Path, engine: LocalEngine | RayEngine,
              progress: Callable[[BatchProgress], None] | None = None) -> dict:
    """Estimate every job not finished before into ``out_root``; writes runs.csv (also when
    interrupted) and returns the batch's summary: counts, the records of ``jobs`` in job
    order, the median ground-truth errors and the wall time."""
    out_root = Path(out_root)
    if out_root.exists() and not out_root.is_dir():
        raise MvtopError(f"{out_root}: exists and is not a folder")
    records_dir = out_root / RECORDS_DIR
    records_dir.mkdir(parents=True, exist_ok=True)
    before = read_records(records_dir)
    todo = [j for j in jobs if not is_finished(j, before.get(j.name))]
    skipped = len(jobs) - len(todo)
    names_todo = {j.name for j in todo}
    records = {j.name: before[j.name] for j in jobs if j.name not in names_todo}
    t0 = time.perf_counter()
    failed = 0

    def report(last: dict | None) -> None:
        if progress is None:
            return
        done = len(records)
        elapsed = time.perf_counter() - t0
        ran = done - skipped
        left = (len(jobs) - done) * elapsed / ran if ran else None
        progress(BatchProgress(done, failed, skipped, len(jobs), elapsed, left, last))

    report(None)
    try:
        for outcome in engine.run(run_estimate_job, [(j, str(records_dir)) for j in todo]):
            job = todo[outcome.index]
            if outcome.error is None:
                rec = outcome.value
            else:  # the job did not return its record (its worker died, Ray gave up): the driver writes it
                rec = {"name": job.name, "log": job.log, "config": job.config, "out": job.out, "key": job.key(),
                       "command": job.command_line(), "status": "failed", "error": one_line(outcome.error),
                       "starts": _count_lines(_starts_path(records_dir, job.name))}
                write_record(records_dir, rec)
            records[job.name] = rec
            failed += rec["status"] != "ok"
            report(rec)
    finally:
        table = write_table(out_root)
    ordered = [records[j.name] for j in jobs]
    ok = [r for r in ordered if r["status"] == "ok"]
    gt = [r for r in ok if r.get("gt_translation_error_mm") is not None]
    return {
        "out": str(out_root), "table": str(table), "engine": engine.describe(), "logs": len(jobs),
        "ok": len(ok), "failed": len(ordered) - len(ok), "skipped": skipped, "ran": len(todo),
        "seconds": round(time.perf_counter() - t0, 3), "records": ordered,
        "gt_logs": len(gt),
        "gt_translation_error_mm_median": float(np.median([r["gt_translation_error_mm"] for r in gt])) if gt else None,
        "gt_rotation_error_deg_median": float(np.median([r["gt_rotation_error_deg"] for r in gt])) if gt else None,
    }


def format_summary(summary: dict) -> str:
    """The batch's summary line."""
    s = summary
    line = (f"estimated {s['logs']} logs into {s['out']} with {s['engine']} in {format_duration(s['seconds'])}: "
            f"{s['ok']} ok, {s['failed']} failed, {s['skipped']} finished before")
    if s["gt_logs"]:
        line += (f"; median error vs ground truth {s['gt_translation_error_mm_median']:.3f} mm, "
                 f"{s['gt_rotation_error_deg_median']:.2f} deg over {s['gt_logs']} logs")
    return line + f"; table {s['table']}"
