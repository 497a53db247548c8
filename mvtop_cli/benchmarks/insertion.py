"""``mvtop benchmark insertion``: the paper's Table I as the paper measures it, in closed loop.

For every object, grasp (a simulation seed) and method (M-VTOP, M-VOP, M-TOP: the modality
sets of ``accuracy.MODALITY_SETS``) one grasp is inserted in closed loop
(``pipelines.insertion``, ``sim.closed_loop``): the online estimator sees the simulated frames
one at a time and the controller aligns the estimated object pose with the receptacle,
descends, and after a stalled descent backs off, re-aligns and retries, up to ``attempts``
attempts. A grasp succeeds when the part reaches the insertion depth (ground truth; see
``sim.closed_loop`` for the compliance). The same seed gives every method the same grasp,
start pose, sensor noise and slip draws. ``scene`` ``hard`` renders the cameras in the harder
scene of ``mvtop simulate --scene hard`` (``pipelines.simulate.HARD_SCENE``); a benchmark folder
holds the runs of one scene.

Like ``benchmark accuracy`` (``runs``: the shared machinery) the runs are independent jobs on
the batch engine (local processes or Ray tasks), each kept as ``OUT/runs/<object>_<seed>_<method>/
result.json``, so an interrupted benchmark resumes where it stopped; ``OUT/results.jsonl.gz``
holds every finished run (one JSON line each), ``OUT/summary.md`` / ``summary.json`` the
tables: success rate per object and method with the average over the objects (Table I),
attempts, and the time to insert. With ``keep_logs`` every attempt is kept as an MCAP log in
``OUT/runs/<run>/logs/`` (read with the config in ``OUT/scenes/<object>/``).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..batch.engine import make_engine
from ..errors import MvtopError
from ..io.atomic import atomic_output
from .accuracy import MODALITY_SETS
from .runs import (
    append_invocation,
    check_settings_apply,
    code_fingerprint,
    masks_note,
    masks_record,
    plan_runs,
    read_jsonl,
    run_jobs,
    scene_record,
    settings_note,
    settings_record,
    simulated_sensors,
    totals,
    write_jsonl_gz,
    write_result,
)

METHODS = tuple(MODALITY_SETS)
RESULTS_FILE = "results.jsonl.gz"
SCHEMA = "mvtop-insertion/1"


@dataclass(frozen=True)
class InsertionBenchmarkOptions:
    objects: tuple[str, ...]
    poses: int = 100  # grasps (simulation seeds) per object
    methods: tuple[str, ...] = METHODS
    attempts: int = 3  # descents per grasp before it counts as failed
    particles: int | None = None  # the config's filter.num_particles when None
    workers: int = 1
    first_seed: int = 1000
    object_files: tuple[tuple[str, str], ...] = ()  # (name, object file path) of objects in ``objects``
    keep_logs: bool = False  # write every attempt as an MCAP log
    import_results: Path | None = None  # a results.jsonl.gz of another benchmark folder
    summary_only: bool = False  # tables over the finished runs; no run is made
    ray: str | None = None  # run the runs as Ray tasks: local, auto or a cluster address (batch/engine.py)
    scene: str = "default"  # simulated camera scene: default, or hard (pipelines.simulate.HARD_SCENE)
    # None: camera masks made from the images (the config's classical backend); N: a segmenter
    # node's masks recorded with the images, outlines off by up to N px (``topic`` backend)
    recorded_masks_px: int | None = None
    settings: dict = field(default_factory=dict)  # {dotted config key: value} over every scene config (--set)


def _run_one(obj: str, seed: int, method: str, run_dir: str, particles: int | None, attempts: int, keep_logs: bool,
             threads: int, source: str | None = None, scene_name: str = "default",
             recorded_masks_px: int | None = None, settings: dict | None = None) -> dict:
    """One grasp in closed loop with one method; writes and returns its report. ``source``:
    the object file of ``obj`` (default: the built-in object of that name); ``scene_name`` the
    simulated camera scene (``default`` or ``hard``); ``recorded_masks_px`` and ``settings``
    as ``InsertionBenchmarkOptions``."""
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    from ..config import load_config
    from ..pipelines.insertion import InsertionOptions, insert, method_config
    from ..pipelines.simulate import write_scene_config
    from ..sim.closed_loop import ControllerOptions

    run = Path(run_dir)
    sensors = simulated_sensors(scene_name, recorded_masks_px)
    cfg_path = run.parent.parent / "scenes" / obj / "config.yaml"
    if not cfg_path.exists():  # two workers may both write it: the same bytes, written atomically
        write_scene_config(source or obj, cfg_path, sensors)
    cfg = method_config(load_config(cfg_path, settings), MODALITY_SETS[method], particles, seed)
    options = InsertionOptions(sensors=sensors, controller=ControllerOptions(attempts=attempts))
    t0, c0 = time.perf_counter(), time.process_time()
    result = insert(source or obj, seed, cfg, options, log_dir=run / "logs" if keep_logs else None)
    report = {
        "schema": SCHEMA,
        "benchmark": {"object": obj, "seed": seed, "method": method, "seconds": time.perf_counter() - t0,
                      "cpu_seconds": time.process_time() - c0, "particles": cfg.filter.num_particles,
                      "attempts_allowed": attempts, "code": code_fingerprint(), **scene_record(scene_name),
                      **masks_record(recorded_masks_px),
                      **settings_record(settings)},
        "insertion": {
            "success": result.success, "attempts": len(result.attempts), "frames": result.frames,
            "rate_hz": result.rate_hz, "time_to_insert_s": result.time_to_insert_s,
            "compliance_mm": options.controller.compliance_m * 1e3,
            "per_attempt": [_attempt_record(a) for a in result.attempts],
        },
    }
    write_result(run, report)
    return report


def _attempt_record(a) -> dict:
    d = asdict(a)
    return {"index": d["index"], "first_frame": d["first_frame"], "last_frame": d["last_frame"],
            "outcome": d["outcome"], "depth_mm": round(d["depth_m"] * 1e3, 4),
            "align_error_mm": round(d["align_error_m"] * 1e3, 4), "align_error_deg": round(d["align_error_deg"], 4)}


def run_insertion_benchmark(out_dir: Path, options: InsertionBenchmarkOptions,
                            progress: Callable[[int, int], None] | None = None) -> dict:
    """Run (or resume) the benchmark into ``out_dir``; returns the summary (also written as
    summary.json and summary.md, and every run in results.jsonl.gz)."""
    out_dir = Path(out_dir)
    unknown = [m for m in options.methods if m not in METHODS]
    if unknown:
        raise MvtopError(f"methods: unknown {', '.join(unknown)} (expected {', '.join(METHODS)})")
    if options.attempts < 1:
        raise MvtopError(f"attempts: expected at least 1, got {options.attempts}")
    files = dict(options.object_files)
    check_settings_apply([files.get(o, o) for o in options.objects], options.settings,
                         simulated_sensors(options.scene, options.recorded_masks_px))
    engine = make_engine(options.workers, options.ray)  # local processes or Ray tasks (batch/engine.py)
    jobs, reports, todo, imported = plan_runs(out_dir, options.objects, options.methods, options.poses,
                                              options.first_seed, options.scene, options.import_results, read_results,
                                              options.summary_only, options.settings, options.recorded_masks_px)
    stale = sorted({r["benchmark"]["attempts_allowed"] for r in reports.values()} - {options.attempts})
    if stale:
        raise MvtopError(f"{out_dir}: its runs were made with --attempts {stale[0]}, not {options.attempts} "
                         "(use that, or another --out)")

    def args_of(key: tuple, run_dir: Path, threads: int) -> tuple:
        o, s, m = key
        return (o, s, m, str(run_dir), options.particles, options.attempts, options.keep_logs, threads, files.get(o),
                options.scene, options.recorded_masks_px, options.settings)

    seconds = run_jobs(_run_one, todo, args_of, reports, len(jobs), engine, progress)
    if not options.summary_only:
        append_invocation(out_dir, options.workers, len(todo), imported, seconds)
    summary = {"objects": list(options.objects), "poses": options.poses, "methods": list(options.methods),
               "attempts": options.attempts, "scene": options.scene, "recorded_masks_px": options.recorded_masks_px,
               "settings": dict(options.settings), "seconds_this_run": round(seconds, 1),
               "runs": len(reports), "runs_requested": len(jobs), "imported_this_run": imported,
               "totals": totals(out_dir, reports), "table": {}}
    for method in options.methods:
        for obj in options.objects:
            rs = [r for (o, _s, m), r in reports.items() if o == obj and m == method]
            if rs:
                summary["table"].setdefault(method, {})[obj] = aggregate(rs)
    write_jsonl_gz(out_dir / RESULTS_FILE, [reports[k] for k in sorted(reports)])
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    with atomic_output(out_dir / "summary.md", "w") as fh:
        fh.write(format_table(summary))
    return summary


def read_results(path: Path) -> list[dict]:
    """The records of an insertion benchmark's ``results.jsonl.gz``; a damaged file or record
    is an error naming the file and line."""
    records = []
    for n, rec in read_jsonl(path, RESULTS_FILE):
        b = rec.get("benchmark") if isinstance(rec, dict) else None
        i = rec.get("insertion") if isinstance(rec, dict) else None
        if (not isinstance(b, dict) or not isinstance(i, dict) or rec.get("schema") != SCHEMA
                or not all(k in b for k in ("object", "seed", "method", "attempts_allowed"))
                or not all(k in i for k in ("success", "attempts", "per_attempt"))):
            raise MvtopError(f"{path} line {n}: expected an insertion record ({SCHEMA}) with benchmark.object/seed/"
                             "method/attempts_allowed and insertion.success/attempts/per_attempt")
        records.append(rec)
    return records


def aggregate(reports: list[dict]) -> dict:
    """Success rate, attempts and times of one object and method's runs."""
    ins = [r["insertion"] for r in reports]
    ok = [i for i in ins if i["success"]]
    times = [i["time_to_insert_s"] for i in ok]
    wall = [r["benchmark"]["seconds"] for r in reports]
    first = [i for i in ins if i["per_attempt"] and i["per_attempt"][0]["outcome"] == "inserted"]
    believed = sum(any(a["outcome"] == "believed_inserted" for a in i["per_attempt"]) for i in ins)
    return {
        "runs": len(ins), "successes": len(ok), "success_rate": len(ok) / len(ins),
        "first_attempt_rate": len(first) / len(ins), "believed_inserted": int(believed),
        "attempts_mean_success": float(np.mean([i["attempts"] for i in ok])) if ok else None,
        "attempts_mean": float(np.mean([i["attempts"] for i in ins])),
        "time_to_insert_s_median": float(np.median(times)) if times else None,
        "seconds_median": float(np.median(wall)),
    }


def format_table(summary: dict) -> str:
    """Markdown: Table I (success rate per object and method, average over the objects), then
    first-attempt success, attempts and the time to insert."""
    objs = summary["objects"]
    t = summary.get("totals", {})
    codes = ", ".join(f"{c} ({n} runs)" for c, n in t.get("code_versions", {}).items())
    done = summary["runs"] == summary["runs_requested"]
    lines = [f"{summary['runs']} of {summary['runs_requested']} runs ({summary['poses']} grasps per object x "
             f"{len(objs)} objects x {len(summary['methods'])} methods, up to {summary['attempts']} attempts"
             f"{'' if summary.get('scene', 'default') == 'default' else ', ' + summary['scene'] + ' scene'}"
             f"{masks_note(summary.get('recorded_masks_px'))}"
             f"{settings_note(summary.get('settings'))})"
             f"{'' if done else ': not complete'}; code {codes}.", ""]

    def table(title: str, cell: Callable[[dict], float | None], fmt: str, average: bool) -> None:
        lines.extend(["", f"**{title}**", "", "| method | " + " | ".join(objs) + (" | avg |" if average else " |"),
                      "|---|" + "---|" * (len(objs) + average)])
        for method, per in summary["table"].items():
            vals = [cell(per[o]) if o in per else None for o in objs]
            cells = ["-" if v is None else format(v, fmt) for v in vals]
            got = [v for v in vals if v is not None]
            avg = ([format(sum(got) / len(got), fmt)] if got else ["-"]) if average else []
            lines.append(f"| {method} | " + " | ".join(cells + avg) + " |")

    table("Insertion success rate, % (Table I)", lambda a: 100 * a["success_rate"], ".0f", True)
    table("Success at the first attempt, %", lambda a: 100 * a["first_attempt_rate"], ".0f", True)
    table("Attempts per successful grasp, mean", lambda a: a["attempts_mean_success"], ".2f", False)
    table("Time to insert, median of the successful grasps [s] (simulated, 10 Hz frames)",
          lambda a: a["time_to_insert_s_median"], ".1f", False)
    table("Wall time per grasp, median [s] (rendering + estimation)", lambda a: a["seconds_median"], ".0f", False)
    return "\n".join(lines[:1] + lines[2:]) + "\n"
