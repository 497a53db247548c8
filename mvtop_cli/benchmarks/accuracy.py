"""``mvtop benchmark accuracy``: the paper's simulated experiments (figure 4, table I).

For every object and grasp (a simulation seed) it simulates an insertion episode, estimates
the pose with each modality set (M-VTOP: vision + touch + contact, M-VOP: vision, M-TOP:
touch) and, when asked, with the CHSEL baseline (point-set registration of the same
observations, the optional ``baseline`` extra: see ``baselines/``), evaluates the final frame
against ground truth, and aggregates per object and method: median and p95 errors (figure 4)
and the insertion success rate, success meaning the final error is within the receptacle's
clearance (table I). Runs are independent processes; each run's report is kept under
``OUT/runs/``, so an interrupted benchmark resumes where it stopped. ``summary.html`` shows
the errors as log-scale box plots per object and method, like the paper's figure 4.

``OUT/results.jsonl.gz`` holds the finished runs the summary covers in compact form (what the
tables need and the per-frame errors, one JSON line per run, tagged with a fingerprint of the
code that made it); given to another
benchmark folder with ``import_results`` it counts those runs as done, which carries a long
benchmark across machines. ``OUT/invocations.jsonl`` records each invocation's wall time.
"""

from __future__ import annotations

import html
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..batch.engine import make_engine
from ..durations import format_duration
from ..errors import MvtopError
from ..eval import report as R
from ..io.atomic import atomic_output
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

MODALITY_SETS = {
    "M-VTOP": ("vision", "tactile", "contact"),
    "M-VOP": ("vision",),
    "M-TOP": ("tactile", "contact"),
}
# Methods that are not the filter: never in the default list, so that the same command gives
# the same tables whether or not their optional dependencies are installed.
BASELINES = ("CHSEL",)
METHODS = tuple(MODALITY_SETS) + BASELINES
# (metric of the eval report's final frame, plot title, unit) of the box plots in summary.html
FIGURE_METRICS = (
    ("pose_error_mm", "Final pose error (mean bounding-box corner distance, paper)", "mm"),
    ("translation_error_mm", "Final translation error", "mm"),
    ("rotation_error_deg", "Final rotation error", "deg"),
)


@dataclass(frozen=True)
class AccuracyOptions:
    objects: tuple[str, ...]
    poses: int = 100  # grasps (simulation seeds) per object
    methods: tuple[str, ...] = tuple(MODALITY_SETS)
    frames: int = 30
    particles: int | None = None
    workers: int = 1
    first_seed: int = 1000
    object_files: tuple[tuple[str, str], ...] = ()  # (name, object file path) of objects in ``objects``
    import_results: Path | None = None  # a results.jsonl.gz of another benchmark folder
    summary_only: bool = False  # tables over the finished runs; no run is made
    ray: str | None = None  # run the runs as Ray tasks: local, auto or a cluster address (batch/engine.py)
    scene: str = "default"  # simulated camera scene: default, or hard (pipelines.simulate.HARD_SCENE)
    # None: camera masks made from the images (the config's classical backend); N: a segmenter
    # node's masks recorded with the images, outlines off by up to N px (``topic`` backend)
    recorded_masks_px: int | None = None
    settings: dict = field(default_factory=dict)  # {dotted config key: value} over every scene config (--set)


RESULTS_FILE = "results.jsonl.gz"
# what a compact record keeps of a run's result.json: all the tables and plots use
_RECORD_KEYS = ("schema", "object", "symmetries", "clearance_mm", "estimate", "final", "before_contact", "benchmark")


def _run_one(obj: str, seed: int, method: str, run_dir: str, frames: int, particles: int | None, threads: int,
             source: str | None = None, scene_name: str = "default", settings: dict | None = None,
             recorded_masks_px: int | None = None) -> dict:
    """Simulate (once per object and seed, shared by the methods), estimate, evaluate. ``source``:
    the object file of ``obj`` (default: the built-in object of that name); ``scene_name`` the
    simulated camera scene (``default`` or ``hard``); ``settings`` ``{dotted config key: value}``
    over the scene config (``--set``); ``recorded_masks_px`` as ``AccuracyOptions``."""
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    from ..config import load_config
    from ..pipelines.estimate import EstimateOptions, estimate
    from ..pipelines.evaluate import evaluate
    from ..pipelines.simulate import simulate, write_scene_config

    run = Path(run_dir)
    scene = run.parent.parent / "scenes" / f"{obj}_{seed}"
    scene.mkdir(parents=True, exist_ok=True)
    log = scene / "log.mcap"
    cfg_path = scene / "config.yaml"
    sensors = simulated_sensors(scene_name, recorded_masks_px, frames)
    simulate_seconds = 0.0
    if not log.exists():
        ts = time.perf_counter()
        simulate(source or obj, seed, log, sensors)
        simulate_seconds = time.perf_counter() - ts
    if not cfg_path.exists():
        write_scene_config(source or obj, cfg_path, sensors)
    cfg = load_config(cfg_path, settings)
    t0, c0 = time.perf_counter(), time.process_time()
    extra = {}
    if method in MODALITY_SETS:
        summary = estimate(log, cfg, run, EstimateOptions(modalities=MODALITY_SETS[method], num_particles=particles,
                                                          seed=seed))
        final = summary["final"]
        extra = {"warning_counts": summary["warning_counts"], "suspect": summary["suspect"],
                 "reported_std": {"translation_mm": 1e3 * final["translation_std_m"],
                                  "rotation_deg": final["rotation_std_deg"]}}
    else:  # the baseline
        from .baselines.chsel_runner import ChselOptions
        from .baselines.run import BaselineOptions, estimate_chsel

        summary = estimate_chsel(log, cfg, run, BaselineOptions(chsel=ChselOptions(threads=threads), seed=seed))
        keys = ("points_seconds", "registration_seconds", "registration_cpu_seconds")
        extra = {k: summary["baseline"][k] for k in keys}
    report = evaluate(run, log, None, run / "eval")
    report["benchmark"] = {"object": obj, "seed": seed, "method": method, "seconds": time.perf_counter() - t0,
                           "cpu_seconds": time.process_time() - c0, "simulate_seconds": simulate_seconds,
                           "code": code_fingerprint(), **scene_record(scene_name), **masks_record(recorded_masks_px),
                           **settings_record(settings),
                           **extra}
    write_result(run, report)
    return report


def run_accuracy(out_dir: Path, options: AccuracyOptions, progress: Callable[[int, int], None] | None = None) -> dict:
    """Run (or resume) the benchmark into ``out_dir``; returns the summary (also written as
    summary.json and summary.md)."""
    from ..pipelines.evaluate import aggregate

    out_dir = Path(out_dir)
    unknown = [m for m in options.methods if m not in METHODS]
    if unknown:
        raise MvtopError(f"methods: unknown {', '.join(unknown)} (expected {', '.join(METHODS)})")
    if any(m in BASELINES for m in options.methods):
        from .baselines.chsel_runner import require

        require()  # a missing extra stops here, before any run, with the pip command
    files = dict(options.object_files)
    check_settings_apply([files.get(o, o) for o in options.objects], options.settings,
                         simulated_sensors(options.scene, options.recorded_masks_px))
    engine = make_engine(options.workers, options.ray)  # local processes or Ray tasks (batch/engine.py)
    jobs, reports, todo, imported = plan_runs(out_dir, options.objects, options.methods, options.poses,
                                              options.first_seed, options.scene, options.import_results, read_results,
                                              options.summary_only, options.settings, options.recorded_masks_px)
    # methods of one scene share its simulated log; two workers may both simulate it, which
    # is harmless: simulation is deterministic and the log is written atomically

    def args_of(key: tuple, run_dir: Path, threads: int) -> tuple:
        o, s, m = key
        return (o, s, m, str(run_dir), options.frames, options.particles, threads, files.get(o), options.scene,
                options.settings, options.recorded_masks_px)

    seconds = run_jobs(_run_one, todo, args_of, reports, len(jobs), engine, progress)
    if not options.summary_only:
        append_invocation(out_dir, options.workers, len(todo), imported, seconds)
    summary = {"objects": list(options.objects), "poses": options.poses, "methods": list(options.methods),
               "scene": options.scene, "recorded_masks_px": options.recorded_masks_px,
               "settings": dict(options.settings),
               "seconds_this_run": round(seconds, 1), "runs": len(reports), "runs_requested": len(jobs),
               "imported_this_run": imported, "totals": totals(out_dir, reports), "table": {}}
    for method in options.methods:
        for obj in options.objects:
            rs = [r for (o, s, m), r in reports.items() if o == obj and m == method]
            if rs:
                agg = aggregate(rs)
                for key in ("seconds", "cpu_seconds", "registration_seconds", "registration_cpu_seconds"):
                    vals = [r["benchmark"][key] for r in rs if key in r.get("benchmark", {})]
                    if vals:
                        agg[key] = {"median": float(np.median(vals)), "p95": float(np.percentile(vals, 95)),
                                    "max": float(np.max(vals))}
                summary["table"].setdefault(method, {})[obj] = agg
    summary["final_errors"] = final_errors(reports, options.objects, options.methods)
    summary["suspect"] = suspect_tally(reports, options.methods)
    write_results(out_dir / RESULTS_FILE, reports)
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    with atomic_output(out_dir / "summary.md", "w") as fh:
        fh.write(format_table(summary))
    with atomic_output(out_dir / "summary.html", "w") as fh:
        fh.write(render_html(summary))
    return summary


_TRACE_KEYS = ("insertion_error_mm", "translation_error_mm", "rotation_error_deg")


def compact_record(report: dict) -> dict:
    """What the tables and plots need of one run's result.json, plus the per-frame errors
    rounded to 0.1 um / 0.0001 deg as ``trace`` (for drift and convergence analyses)."""
    rec = {k: report[k] for k in _RECORD_KEYS if k in report}
    frames = report.get("per_frame")
    if isinstance(frames, list) and frames:
        rec["trace"] = {k: [None if f.get(k) is None else round(float(f[k]), 4) for f in frames] for k in _TRACE_KEYS}
    elif "trace" in report:
        rec["trace"] = report["trace"]
    return rec


def write_results(path: Path, reports: dict[tuple, dict]) -> None:
    """``results.jsonl.gz``: one compact record per run, in (object, seed, method) order;
    byte-identical for the same runs (no time stamp in the gzip header)."""
    write_jsonl_gz(path, [compact_record(reports[key]) for key in sorted(reports)])


def read_results(path: Path) -> list[dict]:
    """The records of a ``results.jsonl.gz`` (or plain ``.jsonl``); a damaged file or record
    is an error naming the file and line."""
    records = []
    for n, rec in read_jsonl(path, RESULTS_FILE):
        b = rec.get("benchmark") if isinstance(rec, dict) else None
        f = rec.get("final") if isinstance(rec, dict) else None
        if (not isinstance(b, dict) or not isinstance(f, dict) or not all(k in b for k in ("object", "seed", "method"))
                or "insertable" not in f or "translation_error_mm" not in f):
            raise MvtopError(f"{path} line {n}: expected a benchmark record with benchmark.object/seed/method "
                             "and final.insertable/translation_error_mm")
        records.append(rec)
    return records


def final_errors(reports: dict[tuple, dict], objects, methods) -> dict:
    """method -> object -> metric -> the final-frame values of every run (seed order), for
    the FIGURE_METRICS."""
    out: dict = {}
    for method in methods:
        for obj in objects:
            rs = [r for (o, s, m), r in sorted(reports.items()) if o == obj and m == method]
            if rs:
                out.setdefault(method, {})[obj] = {k: [r["final"].get(k) for r in rs] for k, _, _ in FIGURE_METRICS}
    return out


SUSPECT_FAR_FACTOR = 5.0  # a run is far off when its final insertion error exceeds this many clearances


def suspect_tally(reports: dict[tuple, dict], methods) -> dict:
    """method -> how the ``suspect_estimate`` warning (filter/health.py) fell: of the runs far
    off (final insertion error above ``SUSPECT_FAR_FACTOR`` clearances) and of those within the
    clearance (``final.insertable``), how many raised it. Only runs that recorded their warnings
    count (results made before they were recorded, and the baseline, have none); methods without
    such runs are left out. Of the flagged runs that recorded why (``benchmark.suspect``, filter/
    health.py ``suspect_causes``): ``{kind}_recorded`` how many, ``{kind}_causes`` per cause how
    many it held in, ``{kind}_alone`` per cause how many it alone raised."""
    out: dict = {}
    for method in methods:
        tally = {"runs": 0, "far_off": 0, "far_off_flagged": 0, "within": 0, "within_flagged": 0}
        for kind in ("far_off", "within"):
            tally.update({f"{kind}_recorded": 0, f"{kind}_causes": {}, f"{kind}_alone": {}})
        for (_, _, m), r in sorted(reports.items()):
            bench, clearance, f = r.get("benchmark", {}), r.get("clearance_mm"), r["final"]
            counts, err = bench.get("warning_counts"), f.get("insertion_error_mm")
            if m != method or counts is None or not clearance or err is None:
                continue
            flagged = counts.get("suspect_estimate", 0) > 0
            causes = bench.get("suspect", {}).get("causes") if flagged else None
            tally["runs"] += 1
            for kind, hit in (("far_off", err > SUSPECT_FAR_FACTOR * clearance), ("within", bool(f["insertable"]))):
                tally[kind] += hit
                tally[f"{kind}_flagged"] += hit and flagged
                if hit and causes is not None:
                    tally[f"{kind}_recorded"] += 1
                    for c in causes:
                        tally[f"{kind}_causes"][c] = tally[f"{kind}_causes"].get(c, 0) + 1
                    if len(causes) == 1:
                        tally[f"{kind}_alone"][causes[0]] = tally[f"{kind}_alone"].get(causes[0], 0) + 1
        if tally["runs"]:
            out[method] = tally
    return out


def _cause_words(t: dict, kind: str) -> str:
    """`` (why: rival_mode 3, unpinned 2 (alone 1); 5 of 6 recorded)`` for the flagged runs of
    ``kind`` that recorded their causes (``suspect_tally``); empty when none did."""
    n = t.get(f"{kind}_recorded", 0)
    if not n:
        return ""
    causes, alone = t[f"{kind}_causes"], t[f"{kind}_alone"]
    words = ", ".join(f"{c} {causes[c]}" + (f" (alone {alone[c]})" if alone.get(c) else "")
                      for c in sorted(causes, key=lambda c: (-causes[c], c)))
    of = "" if n == t[f"{kind}_flagged"] else f"; {n} of {t[f'{kind}_flagged']} recorded"
    return f" (why: {words}{of})"


def figure_svgs(summary: dict) -> list[str]:
    """The log-scale box plots (one per FIGURE_METRICS entry): a box per object and method."""
    objs = summary["objects"]
    methods = [m for m in summary["methods"] if m in summary["final_errors"]]
    figs = []
    for key, title, unit in FIGURE_METRICS:
        series = [(m, [summary["final_errors"][m].get(o, {}).get(key, []) for o in objs]) for m in methods]
        figs.append(R.svg_log_boxplot(objs, series, title=title, ylabel=f"error [{unit}]"))
    return figs


def render_html(summary: dict) -> str:
    """summary.html: one self-contained page with the box plots and the tables."""
    objs = summary["objects"]
    head = ["method"] + objs
    err_rows, rate_rows, time_rows = [], [], []
    for method, per in summary["table"].items():
        err, rate, secs = [method], [method], [method]
        for o in objs:
            a = per.get(o)
            if a is None:
                for row in (err, rate, secs):
                    row.append("–")
                continue
            pe, rot = a["pose_error_mm"], a["rotation_error_deg"]
            err.append(f"{pe['median']:.2f} / {pe['p95']:.2f} mm; {rot['median']:.2f} / {rot['p95']:.2f} deg")
            rate.append(f"{100 * a['success_rate']:.0f} % ({a['runs']} runs)")
            s = a.get("seconds")
            secs.append("–" if s is None else f"{s['median']:.1f} s")
        err_rows.append(err)
        rate_rows.append(rate)
        time_rows.append(secs)
    runs = sum(a["runs"] for per in summary["table"].values() for a in per.values())
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>mvtop benchmark accuracy</title>",
        f"<style>{R.REPORT_CSS}</style></head><body>",
        "<h1>mvtop benchmark accuracy</h1>",
        f"<p>{runs} runs: objects {html.escape(', '.join(objs))}; "
        f"methods {html.escape(', '.join(summary['methods']))}; "
        f"{summary['poses']} grasps per object requested. Final-frame errors against ground truth (mvtop eval, "
        "symmetry-aware). Boxes: quartiles and median; whiskers: 1.5 interquartile ranges; dots: beyond.</p>",
        *figure_svgs(summary),
        "<h2>Final pose error, median / p95 (bounding-box error; rotation)</h2>",
        R.html_table(head, err_rows),
        "<h2>Insertion success rate (final error within the clearance)</h2>",
        R.html_table(head, rate_rows),
        "<h2>Time per run, median (simulation excluded)</h2>",
        R.html_table(head, time_rows),
        "</body></html>",
        "",
    ])


def _header_lines(summary: dict) -> list[str]:
    """What the tables are over: runs done of those requested, the code that made them,
    and the time spent (older summaries without these keys get no header)."""
    t = summary.get("totals")
    if t is None or "runs" not in summary:
        return []
    codes = ", ".join(f"{c} ({n} runs)" for c, n in t["code_versions"].items())
    done = summary["runs"] == summary["runs_requested"]
    missing_sim = t.get("runs_without_simulate_time", 0)
    if missing_sim == summary["runs"]:
        sim = "simulation time not recorded"
    else:
        sim = f"simulation {format_duration(t['simulate_seconds_sum'])}" + (
            f" (not recorded for {missing_sim} runs)" if missing_sim else "")
    wall = (f"{format_duration(t['wall_seconds_all_invocations'])} wall over {t['invocations']} invocation(s) of this "
            "folder; " if t["invocations"] else "")
    lines = [f"{summary['runs']} of {summary['runs_requested']} runs "
             f"({summary['poses']} grasps per object x {len(summary['objects'])} objects x "
             f"{len(summary['methods'])} methods"
             f"{masks_note(summary.get('recorded_masks_px'))}{settings_note(summary.get('settings'))})"
             f"{'' if done else ': not complete'}; code {codes}.",
             f"Time: {wall}the runs (estimate + eval) added up to {format_duration(t['run_seconds_sum'])} wall and "
             f"{format_duration(t['run_cpu_seconds_sum'])} CPU; {sim}.", ""]
    return lines


def format_table(summary: dict) -> str:
    """Markdown tables: median / p95 final errors (figure 4) and success rates (table I)."""
    objs = summary["objects"]
    lines = [*_header_lines(summary),
             "## Final pose error, median / p95 (bounding-box error [mm]; rotation [deg])", "",
             "| method | " + " | ".join(objs) + " |", "|---|" + "---|" * len(objs)]
    for method, per in summary["table"].items():
        cells = []
        for o in objs:
            a = per.get(o)
            if a is None:
                cells.append("-")
                continue
            pe, rot = a["pose_error_mm"], a["rotation_error_deg"]
            cells.append(f"{pe['median']:.2f} / {pe['p95']:.2f} mm; {rot['median']:.2f} / {rot['p95']:.2f} deg")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")

    def rate_table(title: str, key: str) -> None:
        lines.extend(["", f"## {title}, %", "", "| method | " + " | ".join(objs) + " | avg |",
                      "|---|" + "---|" * (len(objs) + 1)])
        for method, per in summary["table"].items():
            rates = [None if per.get(o, {}).get(key) is None else 100 * per[o][key] for o in objs]
            got = [r for r in rates if r is not None]
            avg = f"{sum(got) / len(got):.0f}" if got else "-"
            lines.append(f"| {method} | " + " | ".join("-" if r is None else f"{r:.0f}" for r in rates) + f" | {avg} |")

    rate_table("Insertion success rate (final error within the clearance)", "success_rate")
    if any(a.get("before_contact_runs") for per in summary["table"].values() for a in per.values()):
        rate_table("Within the clearance just before contact (the last frame before the log first reports it)",
                   "before_contact_success_rate")
    if any(a.get("nees_within_bound_fraction") is not None for per in summary["table"].values() for a in per.values()):
        rate_table("Final NEES within its chi-square 95 % bound (the reported covariance against the final error)",
                   "nees_within_bound_fraction")
    if any("seconds" in a for per in summary["table"].values() for a in per.values()):
        lines += ["", "## Time per run, median wall / CPU [s] (estimate + eval; CHSEL: points + registration)", "",
                  "| method | " + " | ".join(objs) + " |", "|---|" + "---|" * len(objs)]
        for method, per in summary["table"].items():
            cells = []
            for o in objs:
                a = per.get(o, {})
                s, cpu = a.get("seconds"), a.get("cpu_seconds")
                reg, reg_cpu = a.get("registration_seconds"), a.get("registration_cpu_seconds")
                cell = "-" if s is None else f"{s['median']:.1f}" + ("" if cpu is None else f" / {cpu['median']:.1f}")
                if reg is not None:
                    cpu_part = "" if reg_cpu is None else f" / {reg_cpu['median']:.1f}"
                    cell += f" (registration {reg['median']:.1f}" + cpu_part + ")"
                cells.append(cell)
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    if summary.get("suspect"):
        lines += ["", f"## suspect_estimate warnings (far off: final insertion error above {SUSPECT_FAR_FACTOR:g} "
                  "clearances)", ""]
        for method, t in summary["suspect"].items():
            lines.append(f"- {method}: far off {t['far_off_flagged']} flagged of {t['far_off']}"
                         f"{_cause_words(t, 'far_off')}; within the clearance {t['within_flagged']} flagged of "
                         f"{t['within']}{_cause_words(t, 'within')} ({t['runs']} runs)")
    return "\n".join(lines) + "\n"
