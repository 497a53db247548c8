"""The CHSEL baseline over a log: observations -> labelled points -> one registration at the
last frame, written as an ``mvtop estimate`` output folder (one track row) so that ``mvtop
eval`` and the accuracy benchmark score it like the filter."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ...config import Config
from ...estimator import FrameEstimate
from ...io.meshes import load_mesh
from ...pipelines.track import run_summary, write_track
from . import chsel_runner
from .observations import LogPoints, PointOptions, log_points, prior_samples

METHOD = "CHSEL"
MODALITIES = ("vision", "tactile")  # the contact signal has no point-set form


@dataclass(frozen=True)
class BaselineOptions:
    points: PointOptions = PointOptions()
    chsel: chsel_runner.ChselOptions = chsel_runner.ChselOptions()
    seed: int = 0
    max_frames: int | None = None


def estimate_chsel(log_path: Path, cfg: Config, out_dir: Path, options: BaselineOptions = BaselineOptions()) -> dict:
    """Register the object to the log's pooled observations with CHSEL, starting from
    ``options.chsel.batch`` poses drawn from the grasp prior (seeded), and write track.mcap,
    track.csv, summary.json and config.resolved.yaml into ``out_dir``; returns the summary,
    whose ``baseline`` block holds the point counts and the seconds spent making points and
    registering. Raises BaselineUnavailable (one line, with the pip command) without chsel."""
    chsel_runner.require()  # fail before the work when the extra is missing
    cfg = replace(cfg, modalities=MODALITIES, filter=replace(cfg.filter, seed=options.seed,
                                                             num_particles=options.chsel.batch))
    t0 = time.perf_counter()
    pts: LogPoints = log_points(log_path, cfg, replace(options.points, seed=options.seed), options.max_frames)
    t_points = time.perf_counter() - t0
    mesh = load_mesh(cfg.object.mesh, cfg.object.units, "object mesh")
    init = prior_samples(cfg, options.chsel.batch, np.random.default_rng(options.seed))
    reg = chsel_runner.register(pts.points, mesh.vertices, mesh.faces, init, options.seed, options.chsel)
    elapsed = time.perf_counter() - t0
    T_ee = reg.T_ref_object
    near = reg.costs <= reg.costs.min() * chsel_runner.COST_RATIO + 1e-12
    result = FrameEstimate(
        index=pts.last_index, stamp_ns=pts.last_stamp_ns, T_ee_object=T_ee, T_world_object=pts.T_world_ee @ T_ee,
        covariance=reg.covariance, ess=float(near.sum()), contact=None, sensors=(), flags=(), mask_mode="points",
        particles_world=pts.T_world_ee @ reg.solutions[np.argsort(reg.costs, kind="stable")],
        T_world_object_gt=pts.T_world_object_gt,
    )
    summary = run_summary([result], cfg, log_path, elapsed, [])
    summary["method"] = METHOD
    summary["frames_processed"] = pts.frames_used
    summary["time_per_frame_s"] = round(elapsed / max(pts.frames_used, 1), 4)
    summary["baseline"] = {
        "method": METHOD,
        "surface_points": int(len(pts.points.surface)),
        "free_points": int(len(pts.points.free)),
        "frames_pooled": pts.frames_used,
        "points_seconds": round(t_points, 3),
        "registration_seconds": round(reg.seconds, 3),
        "registration_cpu_seconds": round(reg.cpu_seconds, 3),
        "batch": int(len(init)),
        "iterations": options.chsel.iterations,
        "resolution_m": options.chsel.resolution_m or chsel_runner.default_resolution_m(mesh.vertices, mesh.faces),
        "best_cost": float(reg.costs.min()),
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_track(out_dir, [result], cfg, summary)
    return summary

