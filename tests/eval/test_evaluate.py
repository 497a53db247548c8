"""``evaluate`` on fake estimate folders: perfect tracks, known offsets, symmetries, files, errors."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import yaml
from _eval_tracks import GT_TOPIC, REPO, STEP_NS, trajectory, write_gt_log, write_track
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mvtop_cli.config import load_config
from mvtop_cli.errors import ConfigError, LogError, MvtopError, TrackError
from mvtop_cli.eval.report import parse_bop_csv
from mvtop_cli.geometry import se3
from mvtop_cli.pipelines.evaluate import aggregate, before_contact, evaluate, object_model, read_gt_file

N = 8


@pytest.fixture(scope="module")
def conn1(tmp_path_factory):
    """Stamps, truth, ee poses and a log with the truth, for conn1."""
    d = tmp_path_factory.mktemp("conn1")
    stamps, T_gt, T_ee = trajectory(N, seed=1)
    return stamps, T_gt, T_ee, write_gt_log(d / "gt.mcap", stamps, T_gt)


def world_offset(T: np.ndarray, d_world) -> np.ndarray:
    out = T.copy()
    out[..., :3, 3] += np.asarray(d_world, dtype=float)
    return out


def lateral_unit(T_gt: np.ndarray) -> np.ndarray:
    """A world direction perpendicular to the truth's z (insertion) axis."""
    z = T_gt[:3, 2]
    v = np.cross(z, [1.0, 0.0, 0.0])
    return v / np.linalg.norm(v)


def test_truth_as_estimate_scores_zero_and_is_insertable(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    track = write_track(tmp_path / "track", "conn1", stamps, T_gt, T_ee)
    report = evaluate(track, log, None, tmp_path / "report")
    f = report["final"]
    for key in ("translation_error_mm", "rotation_error_deg", "pose_error_mm", "add_mm", "adi_mm", "mssd_mm",
                "insertion_error_mm", "translation_error_nosym_mm", "rotation_error_nosym_deg"):
        assert f[key] == pytest.approx(0.0, abs=1e-6), key
    assert f["insertable"] is True
    assert f["nees"] == pytest.approx(0.0, abs=1e-6) and f["nees_within_bound"] is True
    assert report["frames"]["with_truth"] == N and len(report["per_frame"]) == N
    assert report["frames"]["insertable_fraction"] == 1.0
    assert report["frames"]["translation_error_mm"]["p95"] == pytest.approx(0.0, abs=1e-6)
    for name in ("report.json", "report.md", "report.html", "estimates_bop.csv"):
        assert (tmp_path / "report" / name).is_file()
    assert not list((tmp_path / "report").glob(".*"))  # no temporary files left behind


def test_known_lateral_offset_gives_that_error_and_nees(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    d = 1e-4 * lateral_unit(T_gt[-1])  # 0.1 mm, across the insertion axis
    rng = np.random.default_rng(2)
    A = rng.normal(0, 1e-4, (6, 6))
    cov = A @ A.T + np.diag([1e-8] * 3 + [1e-5] * 3)
    track = write_track(tmp_path / "track", "conn1", stamps, world_offset(T_gt, d), T_ee,
                        std_translation_m=1e-4, std_rotation_deg=0.1, final_covariance=cov)
    report = evaluate(track, log, None, tmp_path / "report")
    f = report["final"]
    for key in ("translation_error_mm", "pose_error_mm", "add_mm", "mssd_mm", "insertion_error_mm"):
        assert f[key] == pytest.approx(0.1, abs=1e-6), key
    # ADD-S matches each point to the nearest sample, sometimes a neighbour of its own.
    assert 0.095 < f["adi_mm"] <= f["add_mm"]
    assert f["rotation_error_deg"] == pytest.approx(0.0, abs=1e-6)
    assert f["insertable"] is True  # 0.1 mm <= 0.25 mm clearance (configs/conn1.yaml)
    # NEES by hand: the error in ee axes under the full final covariance.
    e = np.r_[T_ee[-1, :3, :3].T @ -d, np.zeros(3)]  # truth minus estimate
    assert f["nees"] == pytest.approx(float(e @ np.linalg.solve(cov, e)), rel=1e-4)
    # Per frame: diagonal approximation, 0.1 mm error over a 0.1 mm sigma -> NEES 1.
    for row in report["per_frame"][:-1]:
        assert row["nees"] == pytest.approx(1.0, rel=1e-3)
        assert row["nees_within_bound"] is True
    assert report["frames"]["nees_within_bound_fraction"] == 1.0


def test_offsets_beyond_clearance_and_along_the_axis(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    far = evaluate(
        write_track(tmp_path / "a", "conn1", stamps, world_offset(T_gt, 4e-4 * lateral_unit(T_gt[-1])), T_ee),
        log, None, tmp_path / "ra",
    )
    assert far["final"]["insertion_error_mm"] == pytest.approx(0.4, abs=1e-6)
    assert far["final"]["insertable"] is False
    # 1 mm along the insertion axis: a large error, but no lateral misalignment.
    axial = evaluate(write_track(tmp_path / "b", "conn1", stamps, world_offset(T_gt, 1e-3 * T_gt[-1, :3, 2]), T_ee),
                     log, None, tmp_path / "rb")
    assert axial["final"]["translation_error_mm"] == pytest.approx(1.0, abs=1e-6)
    assert axial["final"]["insertion_error_mm"] == pytest.approx(0.0, abs=1e-6)
    assert axial["final"]["insertable"] is True
    # A 1 deg yaw about the insertion axis moves the far corners of the inserted box laterally.
    yaw = evaluate(write_track(tmp_path / "c", "conn1", stamps, T_gt @ se3.make_pose(
        Rotation.from_euler("z", 1.0, degrees=True).as_matrix(), np.zeros(3)), T_ee), log, None, tmp_path / "rc")
    f = yaw["final"]
    assert f["rotation_error_deg"] == pytest.approx(1.0, abs=1e-6)
    # conn1's box spans x in [-11.5, 12.5] mm, y in [-4, 4] mm: farthest corner radius.
    r = math.hypot(12.5, 4.0)
    assert f["insertion_error_mm"] == pytest.approx(2 * r * math.sin(math.radians(0.5)), rel=1e-6)
    assert f["insertable"] is True  # 0.229 mm <= 0.25 mm


def test_report_json_matches_the_bop_csv_and_the_track(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    T_est = T_gt @ se3.exp_se3(np.random.default_rng(4).normal(0, [3e-4] * 3 + [0.01] * 3, (N, 6)))
    track = write_track(tmp_path / "track", "conn1", stamps, T_est, T_ee)
    report = evaluate(track, log, None, tmp_path / "report")
    on_disk = json.loads((tmp_path / "report" / "report.json").read_text())
    assert on_disk["final"]["translation_error_mm"] == pytest.approx(report["final"]["translation_error_mm"], rel=1e-15)
    assert on_disk["final"]["insertable"] == report["final"]["insertable"]
    rows = parse_bop_csv((tmp_path / "report" / "estimates_bop.csv").read_text())
    assert [r["im_id"] for r in rows] == [p["frame"] for p in on_disk["per_frame"]] == list(range(N))
    assert {(r["scene_id"], r["obj_id"]) for r in rows} == {(0, 1)}
    assert all(r["time"] == 0.5 and r["score"] == pytest.approx(0.8) for r in rows)
    for r, T in zip(rows, T_est):
        np.testing.assert_allclose(r["R"], T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(r["t"], T[:3, 3] * 1000.0, atol=1e-9)  # [mm]
    # The final errors recomputed from the CSV row and the report's truth.
    truth = on_disk["final"]["T_world_object_truth"]
    T_truth = se3.from_quat_xyzw(np.array(truth["quaternion_xyzw"]), np.array(truth["translation_m"]))
    assert np.linalg.norm(rows[-1]["t"] - 1000 * T_truth[:3, 3]) == pytest.approx(
        on_disk["final"]["translation_error_mm"], rel=1e-6)
    angle = math.degrees(se3.rotation_angle(rows[-1]["R"], T_truth[:3, :3]))
    assert angle == pytest.approx(on_disk["final"]["rotation_error_deg"], rel=1e-6)
    for row, T, Tg in zip(on_disk["per_frame"], T_est, T_gt):
        assert row["translation_error_mm"] == pytest.approx(1000 * np.linalg.norm(T[:3, 3] - Tg[:3, 3]), rel=1e-6)
    assert on_disk["frames"]["translation_error_mm"]["median"] == pytest.approx(
        float(np.median([r["translation_error_mm"] for r in on_disk["per_frame"]])), rel=1e-12)
    md = (tmp_path / "report" / "report.md").read_text()
    assert f"{on_disk['final']['translation_error_mm']:.3f}" in md and "| metric | value | unit |" in md
    page = (tmp_path / "report" / "report.html").read_text()
    assert page.count("<svg") == 3 and "<script" not in page and "src=" not in page and "href=" not in page
    for svg in page.split("<svg")[1:]:
        ET.fromstring("<svg" + svg.split("</svg>")[0] + "</svg>")  # well-formed inline SVG


def test_ground_truth_file_scores_the_final_frame(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    track = write_track(tmp_path / "track", "conn1", stamps, world_offset(T_gt, [2e-4, 0, 0]), T_ee)
    from_log = evaluate(track, log, None, tmp_path / "r1")
    q = se3.to_quat_xyzw(T_gt[-1])
    gt = tmp_path / "nominal.yaml"
    gt.write_text(yaml.safe_dump({"translation_m": T_gt[-1, :3, 3].tolist(), "quaternion_xyzw": q.tolist()}))
    from_file = evaluate(track, None, gt, tmp_path / "r2")
    assert from_file["ground_truth"]["source"] == "file"
    assert len(from_file["per_frame"]) == 1 and from_file["frames"]["with_truth"] == 1
    for key in ("translation_error_mm", "rotation_error_deg", "mssd_mm", "insertion_error_mm", "nees"):
        assert from_file["final"][key] == pytest.approx(from_log["final"][key], rel=1e-6, abs=1e-9), key
    assert from_file["final"]["translation_error_mm"] == pytest.approx(0.2, abs=1e-6)
    explicit = evaluate(track, None, gt, tmp_path / "r3", config=load_config(REPO / "configs" / "conn1.yaml"))
    assert explicit["final"]["mssd_mm"] == pytest.approx(from_file["final"]["mssd_mm"], rel=1e-12)
    js = tmp_path / "nominal.json"
    js.write_text(json.dumps({"translation_m": T_gt[-1, :3, 3].tolist(), "quaternion_xyzw": q.tolist()}))
    np.testing.assert_allclose(read_gt_file(js), T_gt[-1], atol=1e-12)


def test_sample_log_ground_truth_with_a_known_offset(tmp_path):
    """The truth read from a simulated sample log; the track is that truth shifted 0.3 mm."""
    from mvtop_cli.io.mcap_reader import McapLog

    log = REPO / "sample_logs" / "conn1.mcap"
    with McapLog(log) as reader:
        msgs = [m for m in reader.messages(GT_TOPIC)]
    stamps = np.array([m.log_time_ns for m in msgs], dtype=np.int64)
    T_gt = np.stack([se3.from_quat_xyzw(
        np.array([m.msg.pose.orientation.x, m.msg.pose.orientation.y, m.msg.pose.orientation.z,
                  m.msg.pose.orientation.w]),
        np.array([m.msg.pose.position.x, m.msg.pose.position.y, m.msg.pose.position.z])) for m in msgs])
    T_ee = T_gt @ se3.invert(load_config(REPO / "configs" / "conn1.yaml").grasp_prior.pose.matrix())
    report = evaluate(write_track(tmp_path / "track", "conn1", stamps, world_offset(T_gt, [0, 3e-4, 0]), T_ee),
                      log, None, tmp_path / "r")
    assert report["frames"]["with_truth"] == len(msgs)
    assert report["frames"]["translation_error_mm"]["median"] == pytest.approx(0.3, abs=1e-6)
    assert report["frames"]["translation_error_mm"]["p95"] == pytest.approx(0.3, abs=1e-6)
    assert report["final"]["rotation_error_deg"] == pytest.approx(0.0, abs=1e-6)


def test_before_contact_scores_the_last_frame_before_the_logs_first_contact(tmp_path):
    """A track off by 0.1 mm until the log first reports contact and by 2 mm from then on: the
    report's ``before_contact`` is the frame before that contact message, 0.1 mm off and
    insertable, whatever modalities the track's config enables."""
    from mvtop_cli.io.mcap_reader import McapLog

    log = REPO / "sample_logs" / "conn1.mcap"
    with McapLog(log) as reader:
        msgs = list(reader.messages(GT_TOPIC))
        contact = [(m.log_time_ns, bool(m.msg.data)) for m in reader.messages("/contact")]
    stamps = np.array([m.log_time_ns for m in msgs], dtype=np.int64)
    onset_ns = min(t for t, c in contact if c)
    onset = int(np.searchsorted(stamps, onset_ns))  # the first frame at or after the contact message
    assert 3 < onset < len(stamps) - 3  # the sample log approaches, then touches
    T_gt = np.stack([se3.from_quat_xyzw(
        np.array([m.msg.pose.orientation.x, m.msg.pose.orientation.y, m.msg.pose.orientation.z,
                  m.msg.pose.orientation.w]),
        np.array([m.msg.pose.position.x, m.msg.pose.position.y, m.msg.pose.position.z])) for m in msgs])
    shift = np.where(np.arange(len(stamps)) < onset, 1e-4, 2e-3)
    T_est = T_gt.copy()
    T_est[:, 1, 3] += shift
    T_ee = T_gt @ se3.invert(load_config(REPO / "configs" / "conn1.yaml").grasp_prior.pose.matrix())
    track = write_track(tmp_path / "track", "conn1", stamps, T_est, T_ee)
    cfg = load_config(REPO / "configs" / "conn1.yaml", {"modalities": ["vision"]})
    report = evaluate(track, log, None, tmp_path / "r", config=cfg)
    b = report["before_contact"]
    assert b["contact_frame"] == onset and b["frame"] == onset - 1
    assert b["translation_error_mm"] == pytest.approx(0.1, abs=1e-6) and b["insertable"] is True
    assert report["final"]["translation_error_mm"] == pytest.approx(2.0, abs=1e-6)
    assert json.loads((tmp_path / "r" / "report.json").read_text())["before_contact"] == b


def test_before_contact_is_none_without_contact_or_before_any_frame(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    frames, idx = np.arange(4), np.arange(4)
    rows = [{"frame": i, "insertion_error_mm": 0.1 * i, "translation_error_mm": 0.1 * i, "rotation_error_deg": 0.0,
             "insertable": i < 2} for i in range(4)]
    assert before_contact(None, frames, idx, rows) is None
    assert before_contact([False] * 4, frames, idx, rows) is None
    assert before_contact([True, True, False, True], frames, idx, rows) is None  # in contact from the start
    assert before_contact([None, False, True, True], frames, idx, rows)["frame"] == 1
    # frames without truth are skipped: the last scored frame before the contact
    assert before_contact([False, False, False, True], frames, np.array([0, 1, 3]), [rows[0], rows[1], rows[3]]) == {
        **rows[1], "contact_frame": 3}
    # a log with truth but no TF and sensors gives no contact state: no block
    report = evaluate(write_track(tmp_path / "t", "conn1", stamps, T_gt, T_ee), log, None, tmp_path / "r")
    assert report["before_contact"] is None


def test_ground_truth_is_interpolated_between_messages(tmp_path):
    # Truth at 0, 100, 200 ... ms moving at constant velocity; track frames half-way between.
    n = 6
    stamps = 1_700_000_000_000_000_000 + STEP_NS * np.arange(n, dtype=np.int64)
    R = Rotation.from_euler("xyz", [170, 5, 30], degrees=True).as_matrix()
    T_gt = se3.make_pose(
        np.broadcast_to(R, (n, 3, 3)), np.c_[0.001 * np.arange(n), np.zeros(n), 0.05 - 0.002 * np.arange(n)]
    )
    log = write_gt_log(tmp_path / "gt.mcap", stamps, T_gt)
    mid = stamps[:-1] + STEP_NS // 2
    T_mid = (T_gt[:-1] + T_gt[1:]) / 2  # same rotation, mean translation
    T_ee = T_mid @ se3.invert(se3.make_pose(np.eye(3), (0, 0, 0.0125)))
    report = evaluate(write_track(tmp_path / "track", "conn1", mid, T_mid, T_ee), log, None, tmp_path / "r")
    assert report["frames"]["with_truth"] == n - 1
    assert report["frames"]["translation_error_mm"]["max"] == pytest.approx(0.0, abs=1e-9)


def test_cube_quarter_turn_is_no_error_with_its_symmetries(tmp_path):
    stamps, T_gt, T_ee = trajectory(5, seed=3, object_name="cube")
    log = write_gt_log(tmp_path / "gt.mcap", stamps, T_gt)
    quarter = se3.make_pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.zeros(3))
    report = evaluate(write_track(tmp_path / "track", "cube", stamps, T_gt @ quarter, T_ee), log, None, tmp_path / "r")
    f = report["final"]
    assert report["symmetries"] == 23
    for key in ("translation_error_mm", "rotation_error_deg", "pose_error_mm", "add_sym_mm", "mssd_mm",
                "insertion_error_mm"):
        assert f[key] == pytest.approx(0.0, abs=1e-6), key
    # ADI (BOP's ADD-S) matches points to the nearest surface sample of the turned cube: its
    # samples are not where the truth's are, so it is the sample spacing's error, as in BOP.
    samples = object_model(load_config(REPO / "configs" / "cube.yaml")).samples
    expected = cKDTree(samples @ quarter[:3, :3].T).query(samples)[0].mean() * 1e3
    assert f["adi_mm"] == pytest.approx(expected, abs=1e-9) and 0.1 < f["adi_mm"] < 1.5
    assert f["add_or_adi_mm"] == f["adi_mm"]
    assert f["insertable"] is True and f["symmetry_index"] != 0
    assert f["rotation_error_nosym_deg"] == pytest.approx(90.0, abs=1e-6)
    assert f["add_mm"] > 10.0  # ADD does not know the cube is symmetric
    assert f["nees"] == pytest.approx(0.0, abs=1e-6)


def test_aggregate_over_runs_hand_values():
    def rep(obj, t, ok, nees):
        return {"object": obj, "final": {"translation_error_mm": t, "rotation_error_deg": 2 * t, "insertable": ok,
                                         "nees": nees, "nees_within_bound": nees <= 12.59}}

    runs = [rep("a", 1.0, True, 3.0), rep("a", 2.0, True, 20.0), rep("b", 3.0, False, 5.0), rep("b", 4.0, True, 1.0)]
    agg = aggregate(runs)
    assert agg["runs"] == 4 and agg["successes"] == 3 and agg["success_rate"] == 0.75
    assert agg["translation_error_mm"]["median"] == 2.5
    assert agg["translation_error_mm"]["p95"] == pytest.approx(3.85)  # 3 + 0.85 * (4 - 3), linear
    assert agg["rotation_error_deg"]["max"] == 8.0
    assert agg["nees"]["mean"] == pytest.approx(7.25) and agg["nees_within_bound_fraction"] == 0.75
    assert agg["by_object"]["a"]["success_rate"] == 1.0 and agg["by_object"]["b"]["success_rate"] == 0.5
    assert agg["by_object"]["b"]["translation_error_mm"]["median"] == 3.5
    assert agg["before_contact_runs"] == 0 and agg["before_contact_success_rate"] is None
    runs[0]["before_contact"] = {"insertable": False}
    runs[2]["before_contact"] = {"insertable": True}
    runs[3]["before_contact"] = None  # no contact in that run
    agg = aggregate(runs)
    assert agg["before_contact_runs"] == 2 and agg["before_contact_success_rate"] == 0.5
    assert agg["by_object"]["a"]["before_contact_success_rate"] == 0.0
    b = agg["by_object"]["b"]
    assert b["before_contact_runs"] == 1 and b["before_contact_success_rate"] == 1.0
    with pytest.raises(MvtopError, match="no reports"):
        aggregate([])
    with pytest.raises(MvtopError, match="final.insertable"):
        aggregate([{"object": "a", "final": {}}])


def test_aggregate_accepts_real_reports(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    reports = [evaluate(write_track(tmp_path / f"t{i}", "conn1", stamps, world_offset(T_gt, [d, 0, 0]), T_ee),
                        log, None, tmp_path / f"r{i}") for i, d in enumerate([0.0, 1e-3])]
    agg = aggregate(reports)
    assert agg["runs"] == 2 and agg["success_rate"] == 0.5
    assert agg["translation_error_mm"]["median"] == pytest.approx(0.5, abs=1e-6)


# --- bad inputs ------------------------------------------------------------------------------------


def _break(folder: Path, how: str) -> None:
    csv = folder / "track.csv"
    lines = csv.read_text().splitlines()
    if how == "no_csv":
        csv.unlink()
    elif how == "empty":
        csv.write_text("")
    elif how == "header_only":
        csv.write_text(lines[0] + "\n")
    elif how == "missing_column":
        csv.write_text("\n".join(l.replace(",qw,", ",w,", 1) if i == 0 else l for i, l in enumerate(lines)) + "\n")
    elif how == "not_a_number":
        cells = lines[2].split(",")
        cells[3] = "abc"
        lines[2] = ",".join(cells)
        csv.write_text("\n".join(lines) + "\n")
    elif how == "bad_quaternion":
        cells = lines[1].split(",")
        cells[5:9] = ["0", "0", "0", "2"]
        lines[1] = ",".join(cells)
        csv.write_text("\n".join(lines) + "\n")
    elif how == "no_summary":
        (folder / "summary.json").unlink()
    elif how == "bad_json":
        (folder / "summary.json").write_text("{not json")
    elif how == "no_covariance":
        s = json.loads((folder / "summary.json").read_text())
        del s["final"]["covariance_ee"]
        (folder / "summary.json").write_text(json.dumps(s))
    elif how == "covariance_shape":
        s = json.loads((folder / "summary.json").read_text())
        s["final"]["covariance_ee"] = [[1.0, 0.0], [0.0, 1.0]]
        (folder / "summary.json").write_text(json.dumps(s))
    elif how == "other_run":
        s = json.loads((folder / "summary.json").read_text())
        s["final"]["stamp_ns"] += 1
        (folder / "summary.json").write_text(json.dumps(s))
    elif how == "no_config":
        (folder / "config.resolved.yaml").unlink()


@pytest.mark.parametrize(
    "how, message",
    [
        ("no_csv", r"track\.csv: file not found \(expected the pose track written by mvtop estimate\)"),
        ("empty", r"track\.csv: file is empty"),
        ("header_only", r"track\.csv: no frames"),
        ("missing_column", r"track\.csv: missing column\(s\) qw"),
        ("not_a_number", r"track\.csv: line 3: column 'y_m': expected a number, got 'abc'"),
        ("bad_quaternion", r"track\.csv: line 2: quaternion qx\.\.qw has norm 2"),
        ("no_summary", r"summary\.json: file not found"),
        ("bad_json", r"summary\.json: not valid JSON"),
        ("no_covariance", r"summary\.json: final\.covariance_ee: missing"),
        ("covariance_shape", r"summary\.json: final\.covariance_ee: expected a 6x6 matrix"),
        ("other_run", r"summary\.json: final\.stamp_ns is .* but the last frame of track\.csv"),
        ("no_config", r"config\.resolved\.yaml: file not found"),
    ],
)
def test_malformed_track_folder_raises_track_error(tmp_path, conn1, how, message):
    stamps, T_gt, T_ee, log = conn1
    folder = write_track(tmp_path / "track", "conn1", stamps, T_gt, T_ee)
    _break(folder, how)
    with pytest.raises(TrackError, match=message) as info:
        evaluate(folder, log, None, tmp_path / "report")
    assert "\n" not in str(info.value)
    assert not (tmp_path / "report" / "report.json").exists()


def test_missing_track_folder(tmp_path, conn1):
    with pytest.raises(
        TrackError, match=r"nope: track folder not found \(expected the output folder of mvtop estimate\)"
    ):
        evaluate(tmp_path / "nope", conn1[3], None, tmp_path / "report")


def test_log_without_ground_truth_names_the_topic_and_the_way_out(tmp_path, conn1):
    stamps, T_gt, T_ee, _ = conn1
    track = write_track(tmp_path / "track", "conn1", stamps, T_gt, T_ee)
    bare = write_gt_log(tmp_path / "bare.mcap", stamps, None)
    with pytest.raises(LogError, match=rf"bare\.mcap: no ground truth: topic '{GT_TOPIC}' not found .*--gt FILE"):
        evaluate(track, bare, None, tmp_path / "report")
    with pytest.raises(MvtopError, match="no ground truth"):
        evaluate(track, None, None, tmp_path / "report")
    # A log whose truth ends before the track does.
    short = write_gt_log(tmp_path / "short.mcap", stamps[:3], T_gt[:3])
    with pytest.raises(LogError, match="does not cover the final frame"):
        evaluate(track, short, None, tmp_path / "report")


@pytest.mark.parametrize(
    "content, message",
    [
        ({"translation_m": [0, 0, 0]}, r"quaternion_xyzw: expected a list of 4 numbers, got None"),
        ({"translation_m": [0, 0], "quaternion_xyzw": [0, 0, 0, 1]}, r"translation_m: expected a list of 3 numbers"),
        ({"translation_m": [0, 0, 0], "quaternion_xyzw": [0, 0, 0, 2]}, r"expected a unit quaternion, got norm 2"),
        ({"translation": [0, 0, 0], "quaternion_xyzw": [0, 0, 0, 1]},
         r"translation: unknown key \(did you mean 'translation_m'\?\)"),
    ],
)
def test_bad_ground_truth_file(tmp_path, content, message):
    gt = tmp_path / "gt.yaml"
    gt.write_text(yaml.safe_dump(content))
    with pytest.raises(ConfigError, match=message):
        read_gt_file(gt)
    with pytest.raises(ConfigError, match="ground-truth file not found"):
        read_gt_file(tmp_path / "missing.yaml")


def test_without_a_clearance_insertable_is_n_a(tmp_path, conn1):
    """A config without object.clearance_m: no insertable verdict anywhere, the rest as usual."""
    stamps, T_gt, T_ee, log = conn1
    track = write_track(tmp_path / "track", "conn1", stamps, world_offset(T_gt, 1e-4 * lateral_unit(T_gt[-1])), T_ee)
    cfg_path = track / "config.resolved.yaml"
    data = yaml.safe_load(cfg_path.read_text())
    del data["object"]["clearance_m"]
    cfg_path.write_text(yaml.safe_dump(data))
    report = evaluate(track, log, None, tmp_path / "r")
    f = report["final"]
    assert report["clearance_mm"] is None and f["clearance_mm"] is None and f["insertable"] is None
    assert report["frames"]["insertable_fraction"] is None
    assert all(r["insertable"] is None for r in report["per_frame"])
    assert f["insertion_error_mm"] == pytest.approx(0.1, abs=1e-6)
    md = (tmp_path / "r" / "report.md").read_text()
    assert "n/a (no clearance configured)" in md and "Insertable: n/a" in md
    assert "insertable: n/a" in (tmp_path / "r" / "report.html").read_text()
    agg = aggregate([report])
    assert agg["success_rate"] is None and agg["successes"] is None


def test_bop_csv_named_as_bop_toolkit_expects(tmp_path, conn1):
    stamps, T_gt, T_ee, log = conn1
    track = write_track(tmp_path / "track", "conn1", stamps, T_gt, T_ee)
    report = evaluate(track, log, None, tmp_path / "r", bop_name="mvtop-vt_conn1-test")
    assert report["files"]["bop_csv"] == "mvtop-vt_conn1-test.csv"
    name = (tmp_path / "r" / "mvtop-vt_conn1-test.csv")
    # bop_toolkit's scripts: method = before the first '_', then dataset-split
    method, info = name.stem.split("_", 1)
    assert (method, *info.split("-")) == ("mvtop-vt", "conn1", "test")
    assert len(parse_bop_csv(name.read_text())) == len(stamps)
    for bad in ("mvtop_conn1_test", "mvtop", "my_method_conn1-test", "mvtop_conn-1-test-x-y"):
        with pytest.raises(MvtopError, match="METHOD_DATASET-SPLIT"):
            evaluate(track, log, None, tmp_path / "bad", bop_name=bad)
    assert not (tmp_path / "bad").exists()
