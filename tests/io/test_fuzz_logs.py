"""Reader fuzzing: mutated logs through ``mvtop inspect`` and ``mvtop estimate`` end in one
clear error line or a documented outcome, never a traceback, a hang or a partial output.

The engine is ``scripts/fuzz_logs.py``; its full run (10,000 inputs) is a separate command
(docs/robustness.md). Here: the harness's own checks, every mutation operator on fixed seeds,
a deterministic hypothesis run, and the replay of the regression inputs in fuzz_regressions/
(each crashed or printed more than one line before its fix).
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

REPO = Path(__file__).resolve().parents[2]
REGRESSIONS = Path(__file__).parent / "fuzz_regressions"


def _load_engine():
    spec = importlib.util.spec_from_file_location("fuzz_logs", REPO / "scripts" / "fuzz_logs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["fuzz_logs"] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


fuzz = _load_engine()


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """(worker, config, folder): one worker process for the whole module (numba warm)."""
    folder = tmp_path_factory.mktemp("fuzz")
    config = fuzz.write_config(folder / "config")
    with fuzz.Worker(timeout=120) as worker:
        yield worker, config, folder


def run(env, data: bytes) -> dict[str, tuple[str, str]]:
    worker, config, folder = env
    return fuzz.run_input(worker, data, config, folder, "input")


def assert_clean(res: dict[str, tuple[str, str]], what: str) -> None:
    for command, (outcome, detail) in res.items():
        assert outcome in fuzz.GOOD, f"{command} ended in {outcome!r} on {what}:\n{detail}"


def test_base_log_is_read_and_estimated(env):
    """The unmutated log runs cleanly: the mutants are mutations of a log that works."""
    worker, config, folder = env
    data = fuzz.write_scene(fuzz.base_scene())
    log = folder / "base.mcap"
    log.write_bytes(data)
    r = worker.run(["estimate", str(log), "--config", str(config), "--out", str(folder / "base_out"),
                    "--particles", "10"])
    assert fuzz.classify("estimate", r, log, folder / "base_out") == ("ok", "")
    summary = json.loads((folder / "base_out" / "summary.json").read_text())
    assert summary["frames_processed"] == fuzz.N_FRAMES and summary["frames_skipped"] == 0
    r = worker.run(["inspect", str(log), "--config", str(config)])
    assert fuzz.classify("inspect", r, log, None) == ("ok", "")
    assert "OK: every required topic and TF frame is present." in r["stdout"]
    for layout in fuzz.LAYOUTS:  # every layout of the base log is a valid log
        assert run(env, fuzz.write_scene(fuzz.base_scene(), layout)) == {"inspect": ("ok", ""), "estimate": ("ok", "")}


def test_the_harness_reports_failures(env, tmp_path):
    """The classifier and the time limit really catch what the fuzz test forbids."""
    log = tmp_path / "x.mcap"
    ok = {"code": 0, "stdout": "", "stderr": "", "traceback": None}
    assert fuzz.classify("inspect", ok, log, None)[0] == "ok"
    assert fuzz.classify(
        "inspect", {**ok, "code": None, "traceback": "Traceback ...\nValueError: x"}, log, None
    )[0] == "crash"
    err = {**ok, "code": 2, "stderr": f"mvtop: error: {log}: corrupt chunk\n"}
    assert fuzz.classify("inspect", err, log, None) == ("error", f"mvtop: error: {log}: corrupt chunk")
    assert fuzz.classify("inspect", {**err, "stderr": "libpng error: x\n" + err["stderr"]}, log, None)[0] == "unclear"
    assert fuzz.classify("inspect", {**err, "stderr": "mvtop: error: corrupt chunk\n"}, log, None)[0] == "unclear"
    assert fuzz.classify("inspect", {**ok, "stderr": "Corrupt JPEG data\n"}, log, None)[0] == "noisy"
    # a run longer than a minute prints plain progress lines off a terminal: documented output, not noise
    progress = ("estimate base.mcap: 12/30 (40 %), 1 min 2 s elapsed, about 1 min 30 s left\n"
                "estimate base.mcap: 30/30 (100 %), 2 min 10 s elapsed\n")
    assert fuzz.classify("inspect", {**ok, "stderr": progress}, log, None) == ("ok", "")
    assert fuzz.classify("inspect", {**ok, "stderr": progress + "Corrupt JPEG data\n"}, log, None)[0] == "noisy"
    out = tmp_path / "out"
    out.mkdir()
    (out / "track.csv").write_text("partial")
    assert fuzz.classify("estimate", err, log, out)[0] == "partial"
    assert fuzz.classify("estimate", ok, log, out)[0] == "partial"
    # the time limit: a run that cannot finish in a millisecond is killed and reported
    with fuzz.Worker(timeout=0.001) as slow:
        r = slow.run(["inspect", str(env[1])])
    assert fuzz.classify("inspect", r, log, None)[0] == "hang"


@pytest.mark.parametrize(("program", "answered"), [
    ("import time; time.sleep(1.0); print('{}')", True),  # waits 1 s: under 5 x 0.4 s of wall time
    ("while True: pass", False),  # spins: 0.4 s of CPU time is a hang
    ("import time; time.sleep(60)", False),  # waits on nothing: a hang after 5 x 0.4 s of wall time
])
def test_the_time_limit_counts_cpu_time_and_caps_wall_time(program, answered):
    """A worker that waits (a busy machine, a slow disk) is not hung until five times the limit;
    one that spins is hung after the limit of CPU time, however slowly the machine gives it."""
    worker = fuzz.Worker(timeout=0.4)
    worker.proc = subprocess.Popen([sys.executable, "-c", program], stdout=subprocess.PIPE)
    t0 = time.monotonic()
    try:
        assert worker._answered(worker.timeout) is answered
        assert time.monotonic() - t0 < fuzz.WALL_FACTOR * worker.timeout + 1.0
    finally:
        worker._kill()


@pytest.mark.parametrize("name", sorted(fuzz.MESSAGE_MUTATIONS))
def test_each_message_mutation(env, name):
    for seed in (1, 2):
        spec = fuzz.Spec("zstd", message=((name, seed),))
        data = fuzz.build_input(spec)
        assert data != fuzz.write_scene(fuzz.base_scene()), f"{name} changed nothing"
        assert_clean(run(env, data), spec.describe())


@pytest.mark.parametrize("name", sorted(fuzz.BYTE_MUTATIONS))
def test_each_byte_mutation(env, name):
    for seed, layout in ((1, "none"), (2, "unchunked")):
        spec = fuzz.Spec(layout, byte=((name, seed),))
        assert_clean(run(env, fuzz.build_input(spec)), spec.describe())


def test_chunk_payload_mutation_reaches_the_decoders(env):
    """Changed chunk contents with a recomputed CRC are not stopped by the CRC check."""
    messages = []
    for seed in range(12):
        res = run(env, fuzz.build_input(fuzz.Spec("none", byte=(("chunk_payload", seed),))))
        assert_clean(res, f"chunk_payload@{seed}")
        messages.append(res["estimate"][1])
    assert not all("CRC" in m for m in messages), messages


MUTATIONS = st.tuples(st.sampled_from(sorted(fuzz.MESSAGE_MUTATIONS)), st.integers(0, 2**31 - 1))
BYTES = st.tuples(st.sampled_from(sorted(fuzz.BYTE_MUTATIONS)), st.integers(0, 2**31 - 1))
SPECS = st.builds(
    fuzz.Spec,
    layout=st.sampled_from(fuzz.LAYOUTS),
    message=st.lists(MUTATIONS, max_size=2).map(tuple),
    byte=st.lists(BYTES, max_size=2).map(tuple),
).filter(lambda s: s.message or s.byte)


@settings(max_examples=40, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(spec=SPECS)
def test_mutated_logs_end_cleanly(env, spec):
    assert_clean(run(env, fuzz.build_input(spec)), spec.describe())


EXPECTED = json.loads((REGRESSIONS / "expected.json").read_text())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_regression_inputs(env, name):
    """Inputs that crashed or printed more than one line before their fix (``was``) now end
    in the recorded outcome, with the recorded message."""
    expected = EXPECTED[name]
    data = (REGRESSIONS / name).read_bytes()
    res = run(env, data)
    for command in fuzz.COMMANDS:
        outcome, detail = res[command]
        assert outcome == expected[command]["outcome"], f"{name}: {command}: {outcome}\n{detail}"
        if outcome == "error":
            assert expected[command]["message"] in detail, f"{name}: {command}: {detail}"
    assert sorted(p.name for p in REGRESSIONS.glob("*.mcap")) == sorted(EXPECTED)


# A CameraInfo schema as a ROS 2 recorder stores it: comments, blank lines, aligned columns,
# a constant and a field mvtop does not use, dependencies in their own sections.
RECORDED_CAMERA_INFO = """\
# Calibration of a pinhole camera.
std_msgs/Header header # acquisition time, optical frame

uint32 height   # rows
uint32 width    # columns
string distortion_model
float64[] d
float64[9]  k # row-major 3x3
float64[9]  r
float64[12] p
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
uint8 UNUSED_CONSTANT=3
float64 vendor_extension
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: sensor_msgs/RegionOfInterest
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
"""


def test_schema_check_accepts_recorded_definitions_and_names_what_differs():
    from mvtop_cli.io import ros2_msgs as rm

    assert rm.schema_mismatch(rm.CAMERA_INFO, RECORDED_CAMERA_INFO) is None
    for type_name in rm.MESSAGE_TYPES:
        assert rm.schema_mismatch(type_name, rm.definition(type_name)) is None, type_name
    assert rm.schema_mismatch(rm.CAMERA_INFO, RECORDED_CAMERA_INFO.replace("float64[9]  k", "float64[8]  k")) == (
        "declares the field 'k' of sensor_msgs/msg/CameraInfo as 'float64[8]' (expected 'float64[9]')"
    )
    no_time = RECORDED_CAMERA_INFO.split("=" * 80 + "\nMSG: builtin_interfaces/Time")[0]
    assert rm.schema_mismatch(rm.CAMERA_INFO, no_time) == "has no definition of builtin_interfaces/msg/Time"
    assert rm.schema_mismatch(rm.TF_MESSAGE, rm.definition(rm.TF_MESSAGE).replace("child_frame_id", "child")) == (
        "lacks the field 'child_frame_id' of geometry_msgs/msg/TransformStamped"
    )


def _smooth_jpeg() -> dict:
    import numpy as np

    from mvtop_cli.io.images import encode_compressed

    yy, xx = np.mgrid[0:16, 0:20]
    return encode_compressed(np.stack([xx * 10, yy * 12, (xx + yy) * 5], -1).astype(np.uint8), "jpeg")


def test_codec_diagnostics_go_into_the_error_not_onto_the_terminal(capfd):
    """libjpeg and libpng print to file descriptor 2; the decoder keeps that off the terminal:
    a corrupt stream's message goes into the LogError, a benign one is dropped."""
    from types import SimpleNamespace

    from mvtop_cli.errors import LogError
    from mvtop_cli.io.images import decode_compressed, encode_compressed

    fields = _smooth_jpeg()
    data = fields["data"]
    sof = data.index(b"\xff\xc0")
    extra = data[:sof] + b"\x12\x34" + data[sof:]  # bytes between two segments: benign
    out = decode_compressed(SimpleNamespace(format=fields["format"], data=extra), "/t", (20, 16))
    assert out.shape == (16, 20, 3)
    sos = data.index(b"\xff\xda")
    broken = bytearray(data)
    broken[sos + 20 : sos + 22] = b"\xff\xd3"  # a restart marker inside the scan: partly decoded
    with pytest.raises(LogError, match=r"topic '/t': \d+ bytes do not decode as .*Corrupt JPEG data: premature end"):
        decode_compressed(SimpleNamespace(format=fields["format"], data=bytes(broken)), "/t", (20, 16))
    import numpy as np

    png = bytearray(encode_compressed(np.full((16, 20, 3), 7, np.uint8), "png")["data"])
    png[png.index(b"IDAT") + 8] ^= 0xFF  # zlib stream of the pixels: libpng error
    with pytest.raises(LogError, match=r"libpng error"):
        decode_compressed(SimpleNamespace(format="png", data=bytes(png)), "/t", (20, 16))
    with pytest.raises(LogError, match=r"png image of 30000x30000 px but CameraInfo says 20x16"):
        decode_compressed(SimpleNamespace(format="png", data=fuzz._png_header_bomb(30000, 30000)), "/t", (20, 16))
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""
