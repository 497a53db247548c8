"""Same seed, same track.csv, byte for byte: across runs, across numba thread counts, and
across the accuracy benchmark's worker counts (which give each run 2 or 1 numba threads)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]
LOG, CONFIG = ROOT / "sample_logs" / "cube.mcap", ROOT / "configs" / "cube.yaml"
ARGS = ("--max-frames", "3", "--particles", "100", "--modalities", "vision,tactile", "--seed", "5")


def _mvtop(*args, env: dict | None = None) -> None:
    """The command line in a fresh process (its own numba thread pool)."""
    proc = subprocess.run([sys.executable, "-m", "mvtop_cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr


def _subprocess_run(out: Path, threads: int) -> str:
    _mvtop(
        "estimate", LOG, "--config", CONFIG, "--out", out, *ARGS, env={**os.environ, "NUMBA_NUM_THREADS": str(threads)}
    )
    return (out / "track.csv").read_text()


def test_same_seed_same_track_across_runs_and_numba_threads(tmp_path):
    one = _subprocess_run(tmp_path / "t1", 1)
    two = _subprocess_run(tmp_path / "t2", 2)
    estimate(LOG, load_config(CONFIG), tmp_path / "here",
             EstimateOptions(modalities=("vision", "tactile"), num_particles=100, seed=5, max_frames=3))
    here = (tmp_path / "here" / "track.csv").read_text()
    assert len(one.splitlines()) == 4
    assert one == two == here


def test_benchmark_tracks_do_not_depend_on_the_worker_count(tmp_path):
    """One worker runs each estimate with 2 numba threads, two workers with 1 each."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}  # the benchmark sets it per worker
    for workers in (1, 2):
        _mvtop("benchmark", "accuracy", "--out", tmp_path / f"w{workers}", "--objects", "cube", "--poses", 2,
               "--methods", "M-VTOP", "--frames", 6, "--particles", 100, "--workers", workers, env=env)
    runs = sorted(p.name for p in (tmp_path / "w1" / "runs").iterdir())
    assert runs == ["cube_1000_M-VTOP", "cube_1001_M-VTOP"]
    assert runs == sorted(p.name for p in (tmp_path / "w2" / "runs").iterdir())
    for run in runs:
        a = (tmp_path / "w1" / "runs" / run / "track.csv").read_bytes()
        b = (tmp_path / "w2" / "runs" / run / "track.csv").read_bytes()
        assert len(a.splitlines()) == 7, run
        assert a == b, run
