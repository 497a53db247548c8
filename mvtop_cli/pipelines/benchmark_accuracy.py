"""``mvtop benchmark accuracy``: the paper's simulated experiments (figure 4, table I).

For every object and grasp (a simulation seed) it simulates an insertion episode, estimates
the pose with each modality set (M-VTOP: vision + touch + contact, M-VOP: vision, M-TOP:
touch), evaluates the final frame against ground truth, and aggregates per object and
modality: median and p95 errors (figure 4) and the insertion success rate, success meaning
the final error is within the receptacle's clearance (table I). Runs are independent
processes; each run's report is kept under ``OUT/runs/``, so an interrupted benchmark resumes
where it stopped.
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

from ..io.atomic import atomic_output

MODALITY_SETS = {
    "M-VTOP": ("vision", "tactile", "contact"),
    "M-VOP": ("vision",),
    "M-TOP": ("tactile", "contact"),
}


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
    t0 = time.perf_counter()
    estimate(log, cfg, run, EstimateOptions(modalities=MODALITY_SETS[method], num_particles=particles, seed=seed))
    report = evaluate(run, log, None, run / "eval")
    report["benchmark"] = {"object": obj, "seed": seed, "method": method, "seconds": time.perf_counter() - t0}
    with atomic_output(run / "result.json", "w") as fh:
        json.dump(report, fh)
    return report


def run_accuracy(out_dir: Path, options: AccuracyOptions, progress: Callable[[int, int], None] | None = None) -> dict:
    """Run (or resume) the benchmark into ``out_dir``; returns the summary (also written as
    summary.json and summary.md)."""
    from .evaluate import aggregate

    out_dir = Path(out_dir)
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
                summary["table"].setdefault(method, {})[obj] = aggregate(rs)
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    with atomic_output(out_dir / "summary.md", "w") as fh:
        fh.write(format_table(summary))
    return summary


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
    return "\n".join(lines) + "\n"
