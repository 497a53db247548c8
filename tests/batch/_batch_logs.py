"""A small batch for the batch tests: two copies of the cube sample log and a truncated one,
the serial run each log's outputs must equal, and a way to kill the worker running a job."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

from mvtop_cli.batch.jobs import EstimateJob, jobs_from_arguments
from mvtop_cli.config import load_config
from mvtop_cli.pipelines.checkpoint import CHECKPOINT_DIR, JOURNAL_FILE, frames_done
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]
LOG, CONFIG = ROOT / "sample_logs" / "cube.mcap", ROOT / "configs" / "cube.yaml"
OPTIONS = {"modalities": None, "particles": 30, "seed": 4, "max_frames": 6}
# what differs between two runs of the same command: the time taken, and where a resumed run resumed
TIMING_KEYS = ("run_time_s", "time_per_frame_s", "checkpoint_ms_per_frame", "resumed_at_frame", "timing")


def make_logs(folder: Path) -> list[EstimateJob]:
    """a.mcap and b.mcap (the cube sample log) and bad.mcap (its first 100 kB), as jobs into
    ``folder/out``."""
    logs = folder / "logs"
    logs.mkdir(parents=True)
    shutil.copyfile(LOG, logs / "a.mcap")
    shutil.copyfile(LOG, logs / "b.mcap")
    (logs / "bad.mcap").write_bytes(LOG.read_bytes()[:100_000])
    return jobs_from_arguments([str(logs)], CONFIG, folder / "out", OPTIONS)


def serial_run(job: EstimateJob, folder: Path) -> Path:
    """The job's outputs as a plain single-log estimate makes them (same log path, config and
    options), in ``folder/NAME``."""
    out = folder / job.name
    estimate(Path(job.log), load_config(job.config), out,
             EstimateOptions(modalities=job.modalities, num_particles=job.particles, seed=job.seed,
                             max_frames=job.max_frames))
    return out


def assert_same_outputs(batch_out: Path, serial_out: Path) -> None:
    """track.mcap, track.csv and config.resolved.yaml byte for byte; summary.json equal up to
    its timings."""
    assert sorted(p.name for p in batch_out.iterdir()) == sorted(p.name for p in serial_out.iterdir())
    for name in ("track.mcap", "track.csv", "config.resolved.yaml"):
        assert (batch_out / name).read_bytes() == (serial_out / name).read_bytes(), name
    a, b = (json.loads((d / "summary.json").read_text()) for d in (batch_out, serial_out))
    for key in TIMING_KEYS:
        a.pop(key, None)
        b.pop(key, None)
    assert a == b


def _pid_holding(path: Path) -> int | None:
    """The process that has ``path`` open (Linux /proc), if any."""
    target = str(path)
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            for fd in (proc / "fd").iterdir():
                if os.readlink(fd) == target:
                    return int(proc.name)
        except OSError:
            continue
    return None


def kill_worker_after(out_dir: Path, frames: int, timeout_s: float = 900.0) -> dict:
    """In a background thread: once the job writing ``out_dir`` has checkpointed ``frames``
    frames, SIGKILL the process writing its checkpoint. Returns a dict that gets ``pid`` and
    ``frames`` (those checkpointed when it was killed). The watch gives up after ``timeout_s``:
    generous, as a fresh checkout compiles the kernels in its first workers, which on a busy
    machine takes minutes."""
    killed: dict = {}
    journal = out_dir / CHECKPOINT_DIR / JOURNAL_FILE

    def watch() -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if frames_done(out_dir) >= frames:
                pid = _pid_holding(journal)
                if pid is not None:
                    killed["frames"] = frames_done(out_dir)
                    os.kill(pid, signal.SIGKILL)
                    killed["pid"] = pid
                    return
            time.sleep(0.01)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    killed["thread"] = thread
    return killed
