"""Interrupting ``mvtop estimate`` (SIGKILL, Ctrl-C, SIGTERM) and ``--resume``: no partial output
under the final names, one line saying where it stopped, and a resumed track byte-identical to
an uninterrupted run with the same seed."""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.checkpoint import CHECKPOINT_DIR, EstimateInterrupted, frames_done
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

ROOT = Path(__file__).resolve().parents[2]
LOG = ROOT / "sample_logs" / "cube.mcap"
CONFIG = ROOT / "configs" / "cube.yaml"
FRAMES = 6
ARGS = ["estimate", str(LOG), "--config", str(CONFIG), "--particles", "50", "--max-frames", str(FRAMES)]
OUTPUTS = {"track.mcap", "track.csv", "summary.json", "config.resolved.yaml"}


def mvtop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, timeout=600)


def interrupt_after(out: Path, frames: int, sig: int) -> subprocess.CompletedProcess:
    """Start the estimate into ``out``, send ``sig`` once ``frames`` frames are checkpointed."""
    # a terminal's Ctrl-C disposition, also when the tests run as a background job (which
    # starts with SIGINT ignored, and a child inherits that)
    proc = subprocess.Popen([sys.executable, "-m", "mvtop_cli", *ARGS, "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    while frames_done(out) < frames and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before {frames} frames were checkpointed"
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "out"
    proc = mvtop(*ARGS, "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out


def test_killed_run_resumes_to_the_identical_track(reference, tmp_path):
    out = tmp_path / "out"
    killed = interrupt_after(out, 3, signal.SIGKILL)
    assert killed.returncode == -signal.SIGKILL
    done = frames_done(out)
    assert 3 <= done < FRAMES
    assert not OUTPUTS & {p.name for p in out.iterdir()}  # nothing under a final name
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = out / f".track.csv.{int(gone.stdout)}.0123abcd.tmp"  # as left by a process killed while writing
    stale.write_text("frame,stamp_ns\n0,")
    resumed = mvtop(*ARGS, "--out", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    for name in ("track.csv", "track.mcap"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name
    assert (out / "track.csv").read_text().count("\n") == FRAMES + 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resumed_at_frame"] == done and summary["frames_processed"] == FRAMES
    assert 0 < summary["checkpoint_ms_per_frame"] < 250  # small beside a frame (~0.5-1 s)
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)  # checkpoint and temporaries gone


def test_ctrl_c_exits_130_with_a_resume_hint_and_no_output(tmp_path):
    out = tmp_path / "out"
    stopped = interrupt_after(out, 2, signal.SIGINT)
    assert stopped.returncode == 130, stopped.stderr
    lines = [l for l in stopped.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and "Traceback" not in stopped.stderr, stopped.stderr
    done = frames_done(out)
    assert done >= 2
    assert lines[0].startswith(f"mvtop: interrupted (Ctrl-C) after {done} of {FRAMES} frames; checkpoint in ")
    hint = lines[0].split("; resume with: ", 1)[1]
    assert hint == shlex.join(["mvtop", *ARGS[:4], "--out", str(out), *ARGS[4:], "--resume"])
    assert [p.name for p in out.iterdir()] == [CHECKPOINT_DIR]


def test_sigterm_then_a_checkpoint_of_other_settings_is_refused(tmp_path):
    out = tmp_path / "out"
    stopped = interrupt_after(out, 1, signal.SIGTERM)
    assert stopped.returncode == 143, stopped.stderr
    assert "interrupted (SIGTERM) after" in stopped.stderr and "--resume" in stopped.stderr
    done = frames_done(out)
    assert done >= 1
    refused = mvtop(*ARGS, "--out", str(out), "--resume", "--seed", "7")
    assert refused.returncode == 2
    assert refused.stderr.strip() == (f"mvtop: error: {out / CHECKPOINT_DIR}: cannot resume: config key filter.seed "
                                      "differs (0 in the checkpoint, 7 now); run without --resume to start over")
    assert frames_done(out) == done  # the refused checkpoint is left as it was
    other_log = mvtop("estimate", str(ROOT / "sample_logs" / "plug.mcap"), *ARGS[2:], "--out", str(out), "--resume")
    assert other_log.returncode == 2 and "the log differs (cube.mcap of" in other_log.stderr
    # Without --resume the checkpoint is discarded: a fresh run of 2 frames completes and removes it.
    fresh = mvtop(*ARGS[:-1], "2", "--out", str(out))
    assert fresh.returncode == 0, fresh.stderr
    assert (out / "track.csv").read_text().count("\n") == 3
    assert not (out / CHECKPOINT_DIR).exists()


def test_resume_without_a_checkpoint_is_an_error(tmp_path):
    proc = mvtop(*ARGS, "--out", str(tmp_path / "none"), "--resume")
    assert proc.returncode == 2
    assert "no checkpoint to resume" in proc.stderr and "run without --resume" in proc.stderr
    assert not (tmp_path / "none").exists()


def test_resume_keeps_the_tactile_reference_image(tmp_path):
    """Without depth topics the tactile masks compare with the first tactile image of the log;
    a resumed run must use that one too, not the first image after the checkpoint."""
    raw = yaml.safe_load(CONFIG.read_text())
    for t in raw["sensors"]["tactile"]:
        del t["depth_topic"]
    raw["object"]["mesh"] = str(CONFIG.parent / raw["object"]["mesh"])
    for e in raw["environment"]:
        e["mesh"] = str(CONFIG.parent / e["mesh"])
    path = tmp_path / "difference.yaml"
    path.write_text(yaml.safe_dump(raw))
    cfg = load_config(path)
    options = EstimateOptions(num_particles=30, max_frames=5)
    estimate(LOG, cfg, tmp_path / "ref", options)

    def stop_at_3(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(EstimateInterrupted) as info:
        estimate(LOG, cfg, tmp_path / "run", options, progress=stop_at_3)
    assert info.value.frames_done == 3 and info.value.phase == "frames"
    estimate(LOG, cfg, tmp_path / "run", options, resume=True)
    assert (tmp_path / "run" / "track.csv").read_bytes() == (tmp_path / "ref" / "track.csv").read_bytes()


def test_a_signal_after_the_state_is_written_reports_the_frames_on_disk(tmp_path, monkeypatch):
    """Ctrl-C landing inside ``Checkpoint.record`` after its atomic write of the state but before
    its count in memory: the interruption names the frames the checkpoint holds, which the
    resumed run continues after."""
    from mvtop_cli.pipelines.checkpoint import Checkpoint

    cfg = load_config(CONFIG)
    options = EstimateOptions(num_particles=30, max_frames=4)
    record = Checkpoint.record

    def record_then_stop(self, result, particles, rng, elapsed_s):
        record(self, result, particles, rng, elapsed_s)
        if self.frames_done == 2:
            self.frames_done -= 1  # the state on disk says 2, the count in memory not yet
            raise KeyboardInterrupt

    monkeypatch.setattr(Checkpoint, "record", record_then_stop)
    with pytest.raises(EstimateInterrupted) as info:
        estimate(LOG, cfg, tmp_path / "out", options)
    assert (info.value.phase, info.value.frames_done) == ("frames", 2)
    assert frames_done(tmp_path / "out") == 2
    monkeypatch.setattr(Checkpoint, "record", record)
    summary = estimate(LOG, cfg, tmp_path / "out", options, resume=True)
    assert summary["resumed_at_frame"] == 2 and summary["frames_processed"] == 4


def test_interrupt_while_writing_outputs_keeps_the_checkpoint(tmp_path, monkeypatch):
    import mvtop_cli.pipelines.estimate as pipeline

    cfg = load_config(CONFIG)
    options = EstimateOptions(num_particles=30, max_frames=2)
    write_track = pipeline.write_track

    def write_then_stop(out_dir, results, cfg, summary):
        from mvtop_cli.io.atomic import atomic_output

        with atomic_output(out_dir / "track.csv", "w") as fh:
            fh.write("partial")
            raise KeyboardInterrupt  # in the middle of a file

    monkeypatch.setattr(pipeline, "write_track", write_then_stop)
    with pytest.raises(EstimateInterrupted) as info:
        estimate(LOG, cfg, tmp_path / "out", options)
    assert (info.value.phase, info.value.frames_done) == ("outputs", 2)
    assert [p.name for p in (tmp_path / "out").iterdir()] == [CHECKPOINT_DIR]  # no partial track.csv
    monkeypatch.setattr(pipeline, "write_track", write_track)
    summary = estimate(LOG, cfg, tmp_path / "out", options, resume=True)
    assert summary["resumed_at_frame"] == 2 and summary["frames_processed"] == 2
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(OUTPUTS)
