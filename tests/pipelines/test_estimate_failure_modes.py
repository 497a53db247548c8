"""``mvtop estimate`` on logs and configs that provoke each failure mode for real: the
failure is detected, recovered where possible, listed in summary.json and told once per kind
on stderr; on the clean sample logs nothing is reported."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from mvtop_cli.cli import main
from mvtop_cli.config import load_config
from mvtop_cli.estimator.scene import SceneModel
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

ROOT = Path(__file__).resolve().parents[2]


def _sample(name: str) -> tuple[Path, Path]:
    return ROOT / "sample_logs" / f"{name}.mcap", ROOT / "configs" / f"{name}.yaml"


def _mvtop(capsys, *args) -> tuple[int, str, str]:
    """The command line in this process: (exit code, stdout, stderr)."""
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as stop:
        code = int(stop.code)
    out = capsys.readouterr()
    return code, out.out, out.err


def _estimate(capsys, log, cfg, out, *options) -> tuple[dict, str]:
    code, _, err = _mvtop(capsys, "estimate", log, "--config", cfg, "--out", out, *options)
    assert code == 0, err
    summary = json.loads((Path(out) / "summary.json").read_text())
    return summary, err


def _warning_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("mvtop: warning:")]


def _config(tmp_path: Path, name: str, edit) -> Path:
    """A copy of configs/NAME.yaml with absolute mesh paths, changed by ``edit(dict)``."""
    raw = yaml.safe_load(_sample(name)[1].read_text())
    meshes = ROOT / "configs"
    raw["object"]["mesh"] = str(meshes / raw["object"]["mesh"])
    for e in raw["environment"]:
        e["mesh"] = str(meshes / e["mesh"])
    edit(raw)
    path = tmp_path / f"{name}_edited.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _rewrite(src: Path, dst: Path, topic: str, write) -> None:
    """Copy a log, replacing each message of ``topic`` by what ``write(writer, msg,
    log_time_ns, k)`` writes (``msg`` decoded, ``k`` its index on the topic)."""
    with McapLog(src) as log, LogWriter(dst) as w:
        types = {t.name: t.type for t in log.summary().topics}
        decoded = iter([m.msg for m in log.messages(topic)])
        k = 0
        for m in log.messages(decode=False):
            if m.topic == topic:
                write(w, next(decoded), m.log_time_ns, k)
                k += 1
            else:
                w.write_raw(m.topic, types[m.topic], m.msg, m.log_time_ns, m.publish_time_ns)


def _final_error(summary: dict, log: Path, cfg_path: Path) -> tuple[float, float]:
    """Final (translation [mm], rotation [deg]) error against the log's ground truth, modulo
    the object's symmetries."""
    cfg = load_config(cfg_path)
    f = summary["final"]["T_world_object"]
    T = se3.from_quat_xyzw(np.asarray(f["quaternion_xyzw"]), np.asarray(f["translation_m"]))
    with McapLog(log) as L:
        gt = next(fr.T_world_object_gt for fr in FrameReader(L, sensor_topics(cfg), log_topics(cfg))
                  if fr.stamp_ns == summary["final"]["stamp_ns"])
    errors = []
    for S in [np.eye(4)] + [s.matrix() for s in cfg.object.symmetries]:
        Ts = T @ S
        errors.append((1e3 * float(np.linalg.norm(Ts[:3, 3] - gt[:3, 3])),
                       float(np.degrees(se3.rotation_angle(Ts[:3, :3], gt[:3, :3])))))
    return min(errors, key=lambda e: e[1])


# -- no false alarms ------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["cube", "conn1"])
def test_clean_sample_logs_raise_no_warning(name, capsys, tmp_path):
    """All modalities, the first 8 frames: no warning of any kind, every sensor at full weight."""
    log, cfg = _sample(name)
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--max-frames", 8, "--particles", 150)
    assert summary["warnings"] == [] and summary["warning_counts"] == {}
    assert summary["flags"] == {}
    assert _warning_lines(err) == []
    assert set(summary["sensors"]) == {"left", "right", "front", "side"}
    for name_, s in summary["sensors"].items():
        assert s["weight_factor"] == 1.0 and s["downweighted_at_frame"] is None, name_
        assert s["min_iou_at_estimate"] > 0.7, name_


# -- 1. every weight zero or non-finite -----------------------------------------------------


def test_nan_likelihood_frames_are_skipped_without_nan(capsys, tmp_path, monkeypatch):
    """A broken contact model (NaN signed distances) in frames 2 and 3, the frames in which
    contact is reported: every particle's likelihood is NaN there. The update is skipped (the
    predicted particles carry on), nothing NaN reaches the outputs, the later frames update."""
    src, cfg = _sample("cube")
    log = tmp_path / "contact_2_3.mcap"
    _rewrite(src, log, "/contact", lambda w, msg, t, k: w.write_bool("/contact", k in (2, 3), t))
    monkeypatch.setattr(SceneModel, "phi", lambda self, T: np.full(len(T), np.nan))
    out = tmp_path / "out"
    summary, err = _estimate(capsys, log, cfg, out, "--max-frames", 5, "--particles", 100)
    degenerate = [w for w in summary["warnings"] if w["kind"] == "degenerate_weights"]
    assert [w["frame"] for w in degenerate] == [2, 3]
    assert all(w["invalid"] == w["evaluated"] > 0 for w in degenerate)
    assert summary["warning_counts"]["degenerate_weights"] == 2
    lines = [l for l in _warning_lines(err) if "degenerate_weights" in l]
    assert lines == [
        l for l in lines if "in 2 of 5 frames (2, 3)" in l and "the update was skipped" in l
    ] and len(lines) == 1
    text = (out / "track.csv").read_text()
    assert "nan" not in text.lower() and "inf" not in text.lower()
    rows = list(csv.DictReader(text.splitlines()))
    assert [("degenerate_weights" in r["flags"]) for r in rows] == [False, False, True, True, False]
    assert np.all(np.isfinite(summary["final"]["covariance_ee"]))
    t_err, r_err = _final_error(summary, log, cfg)
    assert t_err < 1.0 and r_err < 2.0  # frame 4 updated normally again


# -- 2. effective sample size collapse ------------------------------------------------------


def test_ess_collapse_is_reported_and_the_frame_redone(capsys, tmp_path):
    """One refinement iteration per frame and a temperature 30x sharper than the default: the
    single tempering stage leaves one particle (ESS ~1 of 100, below the threshold of 2); the
    frame is redone with 24 iterations and its ESS stays at half the particles."""
    log, _ = _sample("conn2")
    cfg = _config(tmp_path, "conn2", lambda c: c.update(filter={"refine_iterations": 1, "temperature": 1e-4}))
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--max-frames", 3, "--particles", 100,
                             "--modalities", "vision,tactile")
    collapsed = [w for w in summary["warnings"] if w["kind"] == "ess_collapsed"]
    assert collapsed and all(w["min_ess"] < w["threshold"] == 2.0 for w in collapsed)
    assert all(w["recovered"] and w["min_ess_after_retry"] > 40 for w in collapsed)
    assert summary["warning_counts"]["ess_collapsed"] == len(collapsed)
    (line,) = [l for l in _warning_lines(err) if "ess_collapsed" in l]
    assert f"in {len(collapsed)} of 3 frames" in line and "redone with 24 tempering iterations" in line
    t_err, r_err = _final_error(summary, log, cfg)
    assert t_err < 0.5 and r_err < 1.0


# -- 3. the estimate jumping further than the motion model allows ---------------------------


def test_slip_beyond_the_motion_model_is_reported_as_a_jump(capsys, tmp_path):
    """A simulated episode whose object slips 2 mm / 3 deg (std) per contact frame in the
    gripper, against the motion model's 0.1 mm / 0.25 deg: the frame where the filter
    follows the slip reports the jump and the bound it exceeds."""
    log, cfg = tmp_path / "slip.mcap", tmp_path / "slip.yaml"
    code, _, err = _mvtop(capsys, "simulate", "--object", "conn1", "--seed", 1, "--frames", 6, "--slip-mm", 2,
                          "--slip-deg", 3, "--out", log, "--write-config", cfg)
    assert code == 0, err
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--particles", 100, "--modalities", "vision,tactile")
    jumps = [w for w in summary["warnings"] if w["kind"] == "estimate_jump"]
    assert jumps, summary["warnings"]
    for w in jumps:
        assert w["frame"] >= 1
        assert w["translation_mm"] > w["allowed_translation_mm"] or w["rotation_deg"] > w["allowed_rotation_deg"]
        assert w["ratio"] > 1.0
        assert f"{w['translation_mm']:.2f} mm / {w['rotation_deg']:.2f} deg" in w["detail"]
        assert f"allows {w['allowed_translation_mm']:.2f} mm / {w['allowed_rotation_deg']:.2f} deg" in w["detail"]
    (line,) = [l for l in _warning_lines(err) if "estimate_jump" in l]
    assert f"in {len(jumps)} of 6 frames" in line and "the motion model allows" in line


# -- 4. a sensor that disagrees with all the others -----------------------------------------


def test_tactile_sensor_with_a_flipped_image_is_named_and_downweighted(capsys, tmp_path):
    """conn1 with the left pad's indentation image upside down (a sensor mounted the other
    way round): it reports contact where the cameras and the other pad see none (IoU ~0.2
    at the estimate against ~0.98). After five frames its weight is scaled by 0.01 and the
    estimate stays accurate; no other sensor is touched."""
    src, cfg = _sample("conn1")
    log = tmp_path / "flipped_left.mcap"

    def flip(w, msg, t, k):
        depth = np.frombuffer(bytes(msg.data), dtype=np.float32).reshape(msg.height, msg.width)
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        w.write_depth("/tactile/left/depth", depth[::-1].copy(), stamp, msg.header.frame_id, log_time_ns=t)

    _rewrite(src, log, "/tactile/left/depth", flip)
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--max-frames", 12, "--particles", 200,
                             "--modalities", "vision,tactile")
    (event,) = [w for w in summary["warnings"] if w["kind"] == "sensor_downweighted"]
    assert event["sensor"] == "left" and event["frame"] == 4  # frames 0-4 disagreeing
    assert event["iou_at_estimate"] < 0.3 and event["others_median_iou"] > 0.9
    assert summary["sensors"]["left"]["weight_factor"] == pytest.approx(0.01)
    assert summary["sensors"]["left"]["downweighted_at_frame"] == 4
    for other in ("right", "front", "side"):
        assert summary["sensors"][other]["weight_factor"] == 1.0
    (line,) = [l for l in _warning_lines(err) if "sensor_downweighted" in l]
    assert "tactile sensor 'left'" in line and "scaled by 0.01" in line
    t_err, r_err = _final_error(summary, log, cfg)
    assert t_err < 1.0 and r_err < 2.5, (t_err, r_err)


# -- 5. meshes that are not watertight -------------------------------------------------------


def _cube_mesh() -> trimesh.Trimesh:
    return trimesh.load(ROOT / "configs" / "meshes" / "cube.obj", force="mesh", process=False)


def _write(mesh_or_arrays, path: Path) -> Path:
    v, f = mesh_or_arrays
    trimesh.Trimesh(v, f, process=False).export(path)
    return path


def test_defective_object_mesh_is_repaired_and_reported(capsys, tmp_path):
    """The cube's mesh with a face missing, a duplicate face and a zero-area face: repaired
    to the closed cube, said so in summary.json and on stderr, and the run goes on."""
    cube = _cube_mesh()
    faces = np.vstack([cube.faces[1:], cube.faces[2:3], [[0, 0, 1]]])
    mesh = _write((cube.vertices, faces), tmp_path / "cube_defective.obj")
    log, _ = _sample("cube")
    cfg = _config(tmp_path, "cube", lambda c: c["object"].update(mesh=str(mesh)))
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--max-frames", 1, "--particles", 40,
                             "--modalities", "vision,tactile")
    (record,) = [w for w in summary["warnings"] if w["kind"] == "mesh_repaired"]
    assert record["frame"] is None and str(mesh) in record["detail"]
    for repair in ("removed 1 degenerate face", "removed 1 duplicate face", "filled holes", "now watertight"):
        assert repair in record["detail"]
    (line,) = [l for l in _warning_lines(err) if "mesh_repaired" in l]
    assert str(mesh) in line


def test_open_object_mesh_is_refused_naming_the_file(capsys, tmp_path):
    """A cube whose top is missing (a hole with 16 edges): no repair closes it, so the run
    stops with one line naming the file; no output is written."""
    box = trimesh.creation.box((0.025, 0.025, 0.025)).subdivide().subdivide()
    keep = box.triangles_center[:, 2] < 0.0124
    mesh = _write((box.vertices, box.faces[keep]), tmp_path / "open_box.obj")
    log, _ = _sample("cube")
    cfg = _config(tmp_path, "cube", lambda c: c["object"].update(mesh=str(mesh)))
    out = tmp_path / "out"
    code, stdout, err = _mvtop(capsys, "estimate", log, "--config", cfg, "--out", out, "--max-frames", 1)
    assert code == 2
    (line,) = err.strip().splitlines()
    assert line.startswith(f"mvtop: error: {mesh}: object mesh is not watertight")
    assert "16 open edges" in line and "inside and outside" in line
    assert not out.exists()


# -- 6. units wrong by 1000x -----------------------------------------------------------------


@pytest.mark.parametrize("which", ["object", "receptacle"])
def test_mesh_in_millimetres_declared_as_metres_is_refused(which, capsys, tmp_path):
    cube = _cube_mesh()
    mesh = _write((1000 * cube.vertices, cube.faces), tmp_path / "in_mm.obj")
    log, _ = _sample("cube")

    def edit(c):
        target = c["object"] if which == "object" else c["environment"][0]
        target.update(mesh=str(mesh), units="m")

    cfg = _config(tmp_path, "cube", edit)
    code, _, err = _mvtop(capsys, "estimate", log, "--config", cfg, "--out", tmp_path / "out", "--max-frames", 1)
    assert code == 2
    (line,) = err.strip().splitlines()
    key = "object.units" if which == "object" else "environment[0].units"
    assert line.startswith(f"mvtop: error: {mesh}: mesh is 25 m across with {key}: 'm'")
    assert f"set {key}: 'mm'" in line
    assert not (tmp_path / "out").exists()


def test_object_out_of_scale_with_the_gripper_is_a_warning(capsys, tmp_path):
    """A 0.6 mm part modelled in millimetres and declared in metres is 0.6 m: possible for a
    long part, so not refused, but 14 times the fingers' size: a units warning."""
    cube = _cube_mesh()
    mesh = _write((24 * cube.vertices, cube.faces), tmp_path / "part_mm.obj")
    log, _ = _sample("cube")
    cfg = _config(tmp_path, "cube", lambda c: c["object"].update(mesh=str(mesh), units="m", symmetries=[]))
    summary, err = _estimate(capsys, log, cfg, tmp_path / "out", "--max-frames", 1, "--particles", 20,
                             "--modalities", "vision")
    (record,) = [w for w in summary["warnings"] if w["kind"] == "units_suspect"]
    assert record["object_extent_m"] == pytest.approx(0.6) and record["ratio"] > 10
    assert "object.units" in record["detail"] and str(mesh) in record["detail"]
    (line,) = [l for l in _warning_lines(err) if "units_suspect" in l]
    assert "check object.units ('m')" in line
