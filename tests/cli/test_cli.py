"""The command line: help, inspect, simulate; bad input gives one line, exit 2, no output."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import yaml
from _real_data import REAL_DATA, needs_real_data

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "sample_logs" / "cube.mcap"
CONFIG = REPO / "configs" / "cube.yaml"
REAL = REAL_DATA / "rosbag2_mcap"


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the installed console script as a user would (real exit codes, real streams)."""
    return subprocess.run(
        [sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, proc.stderr
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    return lines[0]


def test_help_lists_commands_and_options():
    top = run("--help")
    assert top.returncode == 0
    for cmd in ("inspect", "simulate", "estimate"):
        assert cmd in top.stdout
    sim = run("simulate", "--help")
    assert sim.returncode == 0 and "--grasp-translation-mm" in sim.stdout and "--seed" in sim.stdout


def test_inspect_sample_log_with_its_config():
    proc = run("inspect", str(SAMPLE), "--config", str(CONFIG))
    assert proc.returncode == 0, proc.stderr
    assert "/tactile/left/depth" in proc.stdout
    assert "sensor_msgs/msg/CompressedImage" in proc.stdout


@needs_real_data
def test_inspect_real_rosbag2_log_against_a_config_reports_missing_topics():
    proc = run("inspect", str(REAL / "rosbag2_py_test_resources_mcap_talker" / "talker.mcap"), "--config", str(CONFIG))
    line = one_error_line(proc)
    assert "talker.mcap: missing topics" in line and "/cameras/front/image/compressed" in line
    assert "/topic" in proc.stdout  # the report itself is still printed


def test_not_an_mcap_file(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("hello, not a log\n")
    line = one_error_line(run("inspect", str(bad)))
    assert str(bad) in line and "MCAP" in line


def test_truncated_log_is_reported(tmp_path):
    cut = tmp_path / "cut.mcap"
    data = SAMPLE.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    proc = run("inspect", str(cut))
    line = one_error_line(proc)
    assert "cut.mcap" in line and "truncated" in line


def test_missing_log_file(tmp_path):
    line = one_error_line(run("inspect", str(tmp_path / "nope.mcap")))
    assert "nope.mcap" in line


def test_bad_config_key_names_file_and_key(tmp_path):
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["filter"] = {"num_particle": 10}
    path = tmp_path / "bad.yaml"
    shutil.copytree(REPO / "configs" / "meshes", tmp_path / "meshes")
    path.write_text(yaml.safe_dump(cfg))
    line = one_error_line(run("inspect", str(SAMPLE), "--config", str(path)))
    assert line == f"mvtop: error: {path}: filter.num_particle: unknown key (did you mean 'num_particles'?)"


def test_missing_mesh_file(tmp_path):
    cfg = yaml.safe_load(CONFIG.read_text())
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))  # meshes/ is not beside this copy
    line = one_error_line(run("estimate", str(SAMPLE), "--config", str(path), "--out", str(tmp_path / "out")))
    assert "object.mesh: mesh file not found" in line
    assert not (tmp_path / "out").exists()


def test_simulate_list_and_unknown_object(tmp_path):
    proc = run("simulate", "--list")
    assert proc.returncode == 0
    names = [l.split()[0] for l in proc.stdout.splitlines()]
    assert names == ["cube", "shaft_peg", "plug", "conn1", "conn2"]
    line = one_error_line(run("simulate", "--object", "cueb", "--out", str(tmp_path / "x.mcap")))
    assert "'cueb'" in line and "did you mean 'cube'" in line
    assert not (tmp_path / "x.mcap").exists()


def test_simulate_bad_options(tmp_path):
    line = one_error_line(
        run("simulate", "--object", "cube", "--out", str(tmp_path / "x.mcap"), "--resolution", "640by480")
    )
    assert "--resolution" in line
    line = one_error_line(run("simulate", "--object", "cube", "--out", str(tmp_path / "x.txt")))
    assert "x.txt" in line and ".mcap" in line


def test_simulate_writes_a_log_that_inspect_accepts(tmp_path):
    out = tmp_path / "plug.mcap"
    cfg = tmp_path / "plug.yaml"
    proc = run(
        "simulate", "--object", "plug", "--seed", "4", "--frames", "6", "--out", str(out), "--write-config", str(cfg)
    )
    assert proc.returncode == 0, proc.stderr
    assert "6 frames" in proc.stdout
    check = run("inspect", str(out), "--config", str(cfg))
    assert check.returncode == 0, check.stderr
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_unknown_image_format_stops_estimate_without_output(tmp_path):
    from mvtop_cli.io.mcap_reader import McapLog
    from mvtop_cli.io.mcap_writer import LogWriter

    bad = tmp_path / "bad.mcap"
    with McapLog(SAMPLE) as log, LogWriter(bad) as w:
        for m in log.messages(decode=False):
            data = m.msg
            if m.topic == "/cameras/front/image/compressed":
                data = data.replace(b"jpeg compressed", b"h264 compressed")
            w.write_raw(m.topic, m.type, data, m.log_time_ns, m.publish_time_ns)
    out = tmp_path / "out"
    line = one_error_line(run("estimate", str(bad), "--config", str(CONFIG), "--out", str(out), "--particles", "50"))
    assert "bad.mcap" in line and "/cameras/front/image/compressed" in line
    assert "unsupported compressed image format 'rgb8; h264 compressed bgr8'" in line
    assert not out.exists() or not any(out.iterdir())


def test_estimate_writes_the_track_folder(tmp_path):
    out = tmp_path / "run"
    proc = run("estimate", str(SAMPLE), "--config", str(CONFIG), "--out", str(out), "--particles", "100",
               "--max-frames", "3", "--modalities", "vision,tactile")
    assert proc.returncode == 0, proc.stderr
    assert "3 frames" in proc.stdout and "error vs ground truth" in proc.stdout
    # a clean run says nothing on stderr: no library warnings (numba's about an old TBB); only
    # the plain progress lines a run longer than a minute prints off a terminal (a slow machine)
    progress = re.compile(r"^estimate [^:]+: \d+/\d+ \(\d+ %\), .+ elapsed(, about .+ left)?$")
    assert [ln for ln in proc.stderr.splitlines() if not progress.match(ln)] == [], proc.stderr
    assert sorted(p.name for p in out.iterdir()) == ["config.resolved.yaml", "summary.json", "track.csv", "track.mcap"]
    resolved = yaml.safe_load((out / "config.resolved.yaml").read_text())
    assert resolved["modalities"] == ["vision", "tactile"] and resolved["filter"]["num_particles"] == 100
    assert len((out / "track.csv").read_text().splitlines()) == 4

    ev = run("eval", str(out), "--log", str(SAMPLE))
    assert ev.returncode == 0, ev.stderr
    report = __import__("json").loads((out / "eval" / "report.json").read_text())
    assert f"final error {report['final']['translation_error_mm']:.3f} mm" in ev.stdout
    assert sorted(p.name for p in (out / "eval").iterdir()) == [
        "estimates_bop.csv", "report.html", "report.json", "report.md"
    ]
    line = one_error_line(run("eval", str(out)))
    assert "no ground truth" in line


def test_estimate_rejects_unknown_modality(tmp_path):
    line = one_error_line(run("estimate", str(SAMPLE), "--config", str(CONFIG), "--out", str(tmp_path / "o"),
                              "--modalities", "vision,smell"))
    assert "--modalities" in line and "smell" in line


def test_progress_without_a_terminal_prints_plain_lines_with_time_left(monkeypatch, capsys):
    """A long job run into a log file (no terminal) says how far it is and how long is left."""
    from mvtop_cli import cli as cli_module

    clock = iter([0.0, 30.0, 61.0, 90.0, 200.0])
    monkeypatch.setattr(cli_module.time, "monotonic", lambda: next(clock))
    with cli_module._progress("benchmark accuracy") as update:
        update(0, 10)  # t = 0: the start
        update(1, 10)  # t = 30: within the minute, nothing printed
        update(2, 10)  # t = 61: one run in the 31 s since the first, 8 to go at that rate
        update(3, 10)  # t = 90: within a minute of the last line
        update(10, 10)  # t = 200: complete
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        "benchmark accuracy: 2/10 (20 %), 1 min 1 s elapsed, about 4 min 8 s left",
        "benchmark accuracy: 10/10 (100 %), 3 min 20 s elapsed",
    ]


def test_progress_time_left_leaves_out_the_slow_first_frame(monkeypatch, capsys):
    """The first frame compiles the kernels and searches the whole prior (100 s here); the
    time left comes from the frames after it (about 1.5 s each), and there is none while it is the
    only one done."""
    from mvtop_cli import cli as cli_module

    clock = iter([0.0, 100.0, 101.5, 161.2, 176.2])
    monkeypatch.setattr(cli_module.time, "monotonic", lambda: next(clock))
    with cli_module._progress("estimate cube.mcap") as update:
        update(0, 50)  # t = 0: the start
        update(1, 50)  # t = 100: the first frame
        update(2, 50)  # t = 101.5: within the minute
        update(40, 50)  # t = 161.2: 39 frames in the 61.2 s since the first, 10 to go at that rate
        update(50, 50)  # t = 176.2: complete
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        "estimate cube.mcap: 1/50 (2 %), 1 min 40 s elapsed",
        "estimate cube.mcap: 40/50 (80 %), 2 min 41 s elapsed, about 16 s left",
        "estimate cube.mcap: 50/50 (100 %), 2 min 56 s elapsed",
    ]


def test_progress_of_a_short_job_without_a_terminal_prints_nothing(monkeypatch, capsys):
    from mvtop_cli import cli as cli_module

    clock = iter([0.0, 5.0, 12.0])
    monkeypatch.setattr(cli_module.time, "monotonic", lambda: next(clock))
    with cli_module._progress("estimate cube.mcap", resumable=True) as update:
        update(0, 30)
        update(15, 30)
        update(30, 30)
    assert capsys.readouterr().err == ""


def test_inspect_says_in_one_line_when_the_ground_truth_frame_does_not_connect(tmp_path):
    import numpy as np

    from mvtop_cli.geometry.camera import PinholeCamera
    from mvtop_cli.io.mcap_writer import LogWriter

    raw = yaml.safe_load(CONFIG.read_text())
    raw["object"]["mesh"] = str(CONFIG.parent / raw["object"]["mesh"])
    raw["environment"] = []
    raw["modalities"] = ["vision"]
    raw["sensors"] = {"cameras": [{"name": "front", "image_topic": "/cam/image", "info_topic": "/cam/info",
                                   "frame": "front_optical"}], "tactile": []}
    raw.setdefault("topics", {})["ground_truth"] = "/gt"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    log = tmp_path / "log.mcap"
    with LogWriter(log) as w:
        w.write_tf([("world", "front_optical", np.eye(4))], 10**9, static=True)
        for i in range(3):
            t = 10**9 + i * 10**8
            w.write_tf([("world", "ee", np.eye(4))], t)
            w.write_image("/cam/image", np.zeros((6, 8, 3), np.uint8), t, "front_optical")
            w.write_camera_info("/cam/info", PinholeCamera.from_fov(8, 6, 10.0), t, "front_optical")
            w.write_pose("/gt", np.eye(4), t, "tray")
    line = one_error_line(run("inspect", str(log), "--config", str(cfg)))
    assert line == (f"mvtop: error: {log}: ground truth on /gt is in frame 'tray', which TF does not connect to "
                    "'world' (expected its poses in 'world', or a frame on a TF chain to it)")
