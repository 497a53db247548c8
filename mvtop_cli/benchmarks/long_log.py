"""``mvtop benchmark long-log``: memory and time of ``mvtop estimate`` on a log of a few gigabytes.

The log is simulated for the run (never shipped): one long insertion episode of an object
(approach, descent, then contact until the end) with uncompressed images, so that a few
hundred frames make gigabytes: per frame two 640 x 480 rgb8 camera images, two rgb8 tactile
images and two 32FC1 indentation depth maps (about 2.9 MB), in MCAP chunks without
compression, plus TF, joint states, contact, wrench and ground truth. The per-frame slip and
lateral search motion in contact are scaled by sqrt(30 / frames), so the whole episode
slips about as much as a 30-frame one while every frame moves physically consistently.

``mvtop estimate`` then runs on it in a child process, as a user would run it. While it
runs, the child's resident memory (/proc) and the frames it has checkpointed are sampled;
at the end its peak resident memory comes from ``getrusage`` (``wait4``). Reported: log size
and frames, peak RSS, RSS over the first and last quarter of the frames, wall and CPU seconds
per frame over the first and last quarter (equal for a run whose time is linear in the
frames, up to what the frames show: the first quarter is free motion, the last contact) and
over the two halves of the contact phase (like with like), total time and the checkpoint
cost per frame.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import MvtopError
from ..pipelines.checkpoint import progress as checkpoint_progress

_REFERENCE_FRAMES = 30  # the episode length whose total slip a long episode keeps
_POLL_S = 0.5


@dataclass(frozen=True)
class LongLogOptions:
    size_gb: float = 2.0  # target log size [GB = 1e9 bytes]
    particles: int = 200
    object_name: str = "cube"
    seed: int = 0
    keep: Path | None = None  # folder for the log, config and track (kept); default a temporary one


def _episode_options(frames: int):
    from ..sim.episode import EpisodeOptions

    base = EpisodeOptions()
    k = math.sqrt(_REFERENCE_FRAMES / frames) if frames > _REFERENCE_FRAMES else 1.0
    return replace(base, frames=frames, slip_translation_m=base.slip_translation_m * k,
                   slip_rotation_deg=base.slip_rotation_deg * k, wiggle_m=base.wiggle_m * k)


def _simulate_options(frames: int):
    from ..pipelines.simulate import SimulateOptions

    return SimulateOptions(
        episode=_episode_options(frames), image_format="raw", tactile_format="raw", compression="none"
    )


def _write_config(object_name: str, path: Path) -> None:
    """The scene config of ``object_name`` reading the raw (uncompressed) image topics."""
    import yaml

    from ..pipelines.simulate import export_scene_meshes, scene_config

    cfg = scene_config(object_name)
    for group in ("cameras", "tactile"):
        for s in cfg["sensors"][group]:
            s["image_topic"] = s["image_topic"].removesuffix("/compressed")
    export_scene_meshes(path.parent / "meshes", [object_name])
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))


def make_long_log(folder: Path, options: LongLogOptions, progress: Callable[[int, int], None] | None = None) -> dict:
    """Simulate the long log into ``folder`` (log.mcap, config.yaml, meshes/); reuses a log
    made there before with the same object, seed and size. Returns its description."""
    from ..pipelines.simulate import simulate

    log, cfg, meta_path = folder / "log.mcap", folder / "config.yaml", folder / "log.json"
    want = {"object": options.object_name, "seed": options.seed, "size_gb": options.size_gb}
    if log.is_file() and cfg.is_file() and meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if {k: meta.get(k) for k in want} == want:
            return {**meta, "reused": True}
    probe = folder / "probe.mcap"  # bytes per frame from a 4-frame episode
    simulate(options.object_name, options.seed, probe, _simulate_options(4))
    per_frame = probe.stat().st_size / 4
    probe.unlink()
    frames = max(4, math.ceil(options.size_gb * 1e9 / per_frame))
    t0 = time.perf_counter()
    summary = simulate(options.object_name, options.seed, log, _simulate_options(frames), progress=progress)
    _write_config(options.object_name, cfg)
    meta = {**want, "frames": summary.frames, "contact_frames": summary.contact_frames, "bytes": summary.bytes,
            "simulate_s": round(time.perf_counter() - t0, 1)}
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return {**meta, "reused": False}


@dataclass(frozen=True)
class _Sample:
    wall_s: float  # since the child started
    frames: int  # frames checkpointed
    run_s: float  # the estimate's own clock when its last checkpointed frame was done
    rss_mb: float | None
    cpu_s: float | None  # user + system time of the child


def _proc(pid: int) -> tuple[float | None, float | None]:
    """(resident memory [MB], user + system CPU time [s]) of a running process, from /proc."""
    rss = cpu = None
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    rss = int(line.split()[1]) / 1024.0
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        pass
    return rss, cpu


def _per_frame(points: list[tuple[int, float]], lo: int, hi: int) -> float | None:
    """Seconds per frame from frame ``lo`` to frame ``hi`` done, interpolating a clock sampled
    as (frames done, seconds) ``points``."""
    first: dict[int, float] = {}
    for k, t in points:
        if k > 0:
            first.setdefault(k, t)  # the first sample after frame k was done is the closest
    pts = sorted(first.items())
    if hi <= lo or len(pts) < 2 or not pts[0][0] <= lo < hi <= pts[-1][0]:
        return None
    k, t = np.array(pts, dtype=np.float64).T
    return round(float(np.interp(hi, k, t) - np.interp(lo, k, t)) / (hi - lo), 3)


def _contact_flags(track_csv: Path) -> list[bool]:
    import csv

    with open(track_csv) as fh:
        return [row["contact"] == "1" for row in csv.DictReader(fh)]


def run_estimate(folder: Path, particles: int, progress: Callable[[int, int], None] | None = None,
                 total: int = 0) -> dict:
    """Run ``mvtop estimate`` on ``folder``'s log in a child process and measure it."""
    out = folder / "track"
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "mvtop_cli", "estimate", str(folder / "log.mcap"), "--config",
           str(folder / "config.yaml"), "--out", str(out), "--particles", str(particles)]
    samples: list[_Sample] = []
    with open(folder / "estimate.stdout", "w") as so, open(folder / "estimate.stderr", "w") as se:
        t0 = time.perf_counter()
        child = subprocess.Popen(cmd, stdout=so, stderr=se)
        try:
            while True:
                pid, status, usage = os.wait4(child.pid, os.WNOHANG)
                if pid:
                    child.returncode = os.waitstatus_to_exitcode(status)
                    break
                n, run_s = checkpoint_progress(out)
                samples.append(_Sample(time.perf_counter() - t0, n, run_s, *_proc(child.pid)))
                if progress is not None and total:
                    progress(min(n, total), total)
                time.sleep(_POLL_S)
        except BaseException:
            child.kill()
            child.wait()
            raise
        wall_s = time.perf_counter() - t0
    if child.returncode != 0:
        err = (folder / "estimate.stderr").read_text().strip().splitlines()
        raise MvtopError(f"benchmark long-log: mvtop estimate failed (exit {child.returncode}): "
                         f"{err[-1] if err else 'no message'}")
    summary = json.loads((out / "summary.json").read_text())
    n = summary["frames_processed"]
    q = max(n // 4, 2)

    def rss_median(lo: int, hi: int) -> float | None:
        vals = [s.rss_mb for s in samples if lo <= s.frames <= hi and s.rss_mb is not None]
        return round(float(np.median(vals)), 1) if vals else None

    # Like with like: the episode's first part is free motion, the rest contact, where every
    # likelihood also evaluates the contact term; compare the two halves of the contact phase.
    contact = _contact_flags(out / "track.csv")
    first_contact = next((i for i, c in enumerate(contact) if c), n)
    mid = (first_contact + n) // 2
    # The run's own clock at each checkpoint (wall) and the child's CPU time at each sample;
    # the last frame is done when the outputs start being written (the summary's run time).
    wall = [(x.frames, x.run_s) for x in samples] + [(n, summary["run_time_s"])]
    cpu = [(x.frames, x.cpu_s) for x in samples if x.cpu_s is not None] + [(n, usage.ru_utime + usage.ru_stime)]
    return {
        "frames": n,
        "particles": particles,
        "contact_from_frame": first_contact,
        "wall_s": round(wall_s, 1),
        "run_time_s": summary["run_time_s"],
        "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1),  # Linux: kilobytes
        "rss_first_quarter_mb": rss_median(1, q),
        "rss_last_quarter_mb": rss_median(n - q, n),
        "s_per_frame_first_quarter": _per_frame(wall, 1, q),
        "s_per_frame_last_quarter": _per_frame(wall, n - q, n),
        "cpu_s_per_frame_first_quarter": _per_frame(cpu, 1, q),
        "cpu_s_per_frame_last_quarter": _per_frame(cpu, n - q, n),
        "s_per_frame_contact_first_half": _per_frame(wall, first_contact + 1, mid),
        "s_per_frame_contact_last_half": _per_frame(wall, mid, n),
        "cpu_s_per_frame_contact_first_half": _per_frame(cpu, first_contact + 1, mid),
        "cpu_s_per_frame_contact_last_half": _per_frame(cpu, mid, n),
        "checkpoint_ms_per_frame": summary.get("checkpoint_ms_per_frame"),
        "samples": [(round(x.wall_s, 1), x.frames, round(x.run_s, 2), x.rss_mb, x.cpu_s) for x in samples],
    }


def benchmark_long_log(options: LongLogOptions, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Make the long log, estimate on it, measure; returns the figures (see the module docstring).
    ``progress(stage, done, total)`` reports the simulation and the estimate."""
    tmp = None
    if options.keep is not None:
        folder = Path(options.keep)
        folder.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="mvtop-long-log-")
        folder = Path(tmp.name)
    try:
        sim_progress = (lambda d, t: progress("simulate", d, t)) if progress else None
        log = make_long_log(folder, options, sim_progress)
        est_progress = (lambda d, t: progress("estimate", d, t)) if progress else None
        result = run_estimate(folder, options.particles, est_progress, log["frames"])
        return {"folder": str(folder) if tmp is None else None, "log": log, "estimate": result}
    finally:
        if tmp is not None:
            tmp.cleanup()
