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
"""

from __future__ import annotations

import html
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..eval import report as R
from ..errors import MvtopError
from ..io.atomic import atomic_output

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


def _run_one(obj: str, seed: int, method: str, run_dir: str, frames: int, particles: int | None, threads: int) -> dict:
    """Simulate (once per object and seed, shared by the methods), estimate, evaluate."""
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    from ..config import load_config
    from ..sim.episode import EpisodeOptions
    from .estimate import EstimateOptions, estimate
    from .evaluate import evaluate
    from .simulate import SimulateOptions, simulate, write_scene_config

    run = Path(run_dir)
    scene = run.parent.parent / "scenes" / f"{obj}_{seed}"
    scene.mkdir(parents=True, exist_ok=True)
    log = scene / "log.mcap"
    cfg_path = scene / "config.yaml"
    if not log.exists():
        simulate(obj, seed, log, SimulateOptions(episode=EpisodeOptions(frames=frames)))
    if not cfg_path.exists():
        write_scene_config(obj, cfg_path)
    cfg = load_config(cfg_path)
    t0, c0 = time.perf_counter(), time.process_time()
    extra = {}
    if method in MODALITY_SETS:
        estimate(log, cfg, run, EstimateOptions(modalities=MODALITY_SETS[method], num_particles=particles, seed=seed))
    else:  # the baseline
        from ..baselines.chsel_runner import ChselOptions
        from ..baselines.run import BaselineOptions, estimate_chsel

        summary = estimate_chsel(log, cfg, run, BaselineOptions(chsel=ChselOptions(threads=threads), seed=seed))
        extra = {k: summary["baseline"][k] for k in ("points_seconds", "registration_seconds", "registration_cpu_seconds")}
    report = evaluate(run, log, None, run / "eval")
    report["benchmark"] = {"object": obj, "seed": seed, "method": method, "seconds": time.perf_counter() - t0,
                           "cpu_seconds": time.process_time() - c0, **extra}
    with atomic_output(run / "result.json", "w") as fh:
        json.dump(report, fh)
    return report


def run_accuracy(out_dir: Path, options: AccuracyOptions, progress: Callable[[int, int], None] | None = None) -> dict:
    """Run (or resume) the benchmark into ``out_dir``; returns the summary (also written as
    summary.json and summary.md)."""
    from .evaluate import aggregate

    out_dir = Path(out_dir)
    unknown = [m for m in options.methods if m not in METHODS]
    if unknown:
        raise MvtopError(f"methods: unknown {', '.join(unknown)} (expected {', '.join(METHODS)})")
    if any(m in BASELINES for m in options.methods):
        from ..baselines.chsel_runner import require

        require()  # a missing extra stops here, before any run, with the pip command
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    jobs = []
    # grasp-major order, so a partial (interrupted) benchmark holds the same grasps of every
    # object and method, and its tables compare like with like
    for i in range(options.poses):
        seed = options.first_seed + i
        for obj in options.objects:
            for method in options.methods:
                run_dir = out_dir / "runs" / f"{obj}_{seed}_{method}"
                jobs.append((obj, seed, method, run_dir))
    reports: dict[tuple, dict] = {}
    todo = []
    for job in jobs:
        result = job[3] / "result.json"
        if result.is_file():
            reports[job[:3]] = json.loads(result.read_text())
        else:
            todo.append(job)
    done = len(reports)
    if progress is not None:
        progress(done, len(jobs))
    threads = max(1, (os.cpu_count() or 1) // max(1, options.workers))
    t0 = time.perf_counter()
    if options.workers <= 1:
        for obj, seed, method, run_dir in todo:
            reports[(obj, seed, method)] = _run_one(obj, seed, method, str(run_dir), options.frames, options.particles, threads)
            done += 1
            if progress is not None:
                progress(done, len(jobs))
    else:
        # methods of one scene share its simulated log; two workers may both simulate it, which
        # is harmless: simulation is deterministic and the log is written atomically
        with ProcessPoolExecutor(max_workers=options.workers) as pool:
            futures = {pool.submit(_run_one, o, s, m, str(d), options.frames, options.particles, threads): (o, s, m)
                       for o, s, m, d in todo}
            for fut in as_completed(futures):
                reports[futures[fut]] = fut.result()
                done += 1
                if progress is not None:
                    progress(done, len(jobs))
    summary = {"objects": list(options.objects), "poses": options.poses, "methods": list(options.methods),
               "seconds_this_run": round(time.perf_counter() - t0, 1), "table": {}}
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
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    with atomic_output(out_dir / "summary.md", "w") as fh:
        fh.write(format_table(summary))
    with atomic_output(out_dir / "summary.html", "w") as fh:
        fh.write(render_html(summary))
    return summary


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
        f"<style>{R._CSS}</style></head><body>",
        "<h1>mvtop benchmark accuracy</h1>",
        f"<p>{runs} runs: objects {html.escape(', '.join(objs))}; methods {html.escape(', '.join(summary['methods']))}; "
        f"{summary['poses']} grasps per object requested. Final-frame errors against ground truth (mvtop eval, "
        "symmetry-aware). Boxes: quartiles and median; whiskers: 1.5 interquartile ranges; dots: beyond.</p>",
        *figure_svgs(summary),
        "<h2>Final pose error, median / p95 (bounding-box error; rotation)</h2>",
        R._html_table(head, err_rows),
        "<h2>Insertion success rate (final error within the clearance)</h2>",
        R._html_table(head, rate_rows),
        "<h2>Time per run, median (simulation excluded)</h2>",
        R._html_table(head, time_rows),
        "</body></html>",
        "",
    ])


def format_table(summary: dict) -> str:
    """Markdown tables: median / p95 final errors (figure 4) and success rates (table I)."""
    objs = summary["objects"]
    lines = ["## Final pose error, median / p95 (bounding-box error [mm]; rotation [deg])", "",
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
    lines += ["", "## Insertion success rate (final error within the clearance), %", "",
              "| method | " + " | ".join(objs) + " | avg |", "|---|" + "---|" * (len(objs) + 1)]
    for method, per in summary["table"].items():
        rates = [100 * per[o]["success_rate"] if o in per else None for o in objs]
        got = [r for r in rates if r is not None]
        cells = ["-" if r is None else f"{r:.0f}" for r in rates]
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {sum(got) / len(got):.0f} |" if got else " | - |")
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
                    cell += f" (registration {reg['median']:.1f}" + ("" if reg_cpu is None else f" / {reg_cpu['median']:.1f}") + ")"
                cells.append(cell)
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
