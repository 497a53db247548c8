"""eval on a recorded log: ground truth in another TF frame, and MSPD per camera.

The shipped cube sample log is rewritten with its ground truth as a PoseStamped in ``ee``
(converted through the log's own TF); ``eval`` must give the same numbers on both logs, and
per camera the MSPD that bop_toolkit's definition gives with the log's calibration and TF.
"""

from __future__ import annotations

import numpy as np
import pytest
from _eval_tracks import GT_TOPIC, REPO, write_track

from mvtop_cli.config import load_config
from mvtop_cli.errors import LogError
from mvtop_cli.eval import metrics as M
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.io.mcap_writer import LogWriter
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.evaluate import evaluate, object_model

SAMPLE = REPO / "sample_logs" / "cube.mcap"
CFG = load_config(REPO / "configs" / "cube.yaml")


def truth_in_world(n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first ``n`` ground-truth stamps of the sample, the truth and ``T_world_ee`` there."""
    with McapLog(SAMPLE) as log:
        reader = FrameReader(log, sensor_topics(CFG), log_topics(CFG))
        msgs = [m for _, m in zip(range(n), log.messages(GT_TOPIC))]
        stamps = np.array([m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec for m in msgs], dtype=np.int64)
        T_gt = np.stack([reader.ground_truth_at(int(s)) for s in stamps])
        T_world_ee = np.stack([reader.tf.lookup("world", "ee", int(s)) for s in stamps])
    return stamps, T_gt, T_world_ee


def rewrite_truth_in(path, frame: str):
    """The sample log with every ground-truth message re-expressed in ``frame`` via its TF."""
    with McapLog(SAMPLE) as log:
        reader = FrameReader(log, sensor_topics(CFG), log_topics(CFG))
        reader.load()
        with LogWriter(path) as w:
            for m in log.messages(decode=False):
                if m.topic != GT_TOPIC:
                    w.write_raw(m.topic, m.type, bytes(m.msg), m.log_time_ns, m.publish_time_ns)
                    continue
                stamp = int(m.log_time_ns)
                T_world_obj = reader.ground_truth_at(stamp)
                w.write_pose(GT_TOPIC, reader.tf.lookup(frame, "world", stamp) @ T_world_obj, stamp, frame,
                             log_time_ns=m.log_time_ns)
    return path


@pytest.fixture(scope="module")
def track(tmp_path_factory):
    d = tmp_path_factory.mktemp("frames")
    stamps, T_gt, T_world_ee = truth_in_world()
    off = se3.make_pose(np.eye(3), (0.0004, -0.0002, 0.0003))  # 0.54 mm off in the object frame
    turn = se3.exp_se3(np.array([0, 0, 0, 0.0, 0.0, np.radians(0.4)]))
    return write_track(d / "track", "cube", stamps, T_gt @ off @ turn, T_world_ee), d


def test_truth_in_ee_gives_the_same_report_as_in_world(track):
    folder, d = track
    world = evaluate(folder, SAMPLE, None, d / "r_world", config=CFG)
    ee_log = rewrite_truth_in(d / "gt_in_ee.mcap", "ee")
    with McapLog(ee_log) as log:
        assert {str(m.msg.header.frame_id) for m in log.messages(GT_TOPIC)} == {"ee"}
    ee = evaluate(folder, ee_log, None, d / "r_ee", config=CFG)
    assert world["ground_truth"]["frame"] == "world" and ee["ground_truth"]["frame"] == "ee"
    for key in ("translation_error_mm", "rotation_error_deg", "add_mm", "adi_mm", "mssd_mm", "pose_error_mm"):
        assert ee["final"][key] == pytest.approx(world["final"][key], abs=1e-6), key
        assert world["final"][key] > 0.05, key
    for cam in ("front", "side"):
        assert ee["final"]["mspd_px"][cam] == pytest.approx(world["final"]["mspd_px"][cam], abs=1e-6)


def test_mspd_per_camera_is_bops_with_the_logs_calibration(track):
    folder, d = track
    rep = evaluate(folder, SAMPLE, None, d / "r_mspd", config=CFG)
    stamps, T_gt, _ = truth_in_world()
    model = object_model(CFG)
    T_est = T_gt @ se3.make_pose(np.eye(3), (0.0004, -0.0002, 0.0003)) @ se3.exp_se3(
        np.array([0, 0, 0, 0.0, 0.0, np.radians(0.4)]))
    with McapLog(SAMPLE) as log:
        reader = FrameReader(log, sensor_topics(CFG), log_topics(CFG))
        for cam, frame in (("front", "front_optical"), ("side", "side_optical")):
            K = reader.camera_at(cam, int(stamps[-1])).K
            T_cam_world = reader.tf.lookup(frame, "world", int(stamps[-1]))
            est, gt = T_cam_world @ T_est[-1], T_cam_world @ T_gt[-1]

            def project(T, K=K):
                x = (model.mesh_vertices @ T[:3, :3].T + T[:3, 3]) @ K.T
                return x[:, :2] / x[:, 2:3]

            # bop_toolkit's loop: symmetries on the truth, max over vertices, min over symmetries
            want = min(np.linalg.norm(project(est) - project(gt @ S), axis=1).max() for S in model.group)
            assert rep["final"]["mspd_px"][cam] == pytest.approx(want, abs=1e-9)
            assert 0.1 < want < 50
            assert rep["frames"]["mspd_px"][cam]["max"] >= want - 1e-9
    assert float(M.mspd(est, gt, K, model.mesh_vertices, model.group)) == pytest.approx(want, abs=1e-9)


def test_truth_in_a_frame_tf_does_not_know_is_one_clear_error(track):
    folder, d = track
    bad = rewrite_truth_in(d / "gt_in_tool.mcap", "ee")
    # rename the frame to one TF never names
    out = d / "gt_in_unknown.mcap"
    with McapLog(bad) as log, LogWriter(out) as w:
        for m in log.messages(decode=False):
            if m.topic == GT_TOPIC:
                full = next(x for x in log.messages(GT_TOPIC, m.log_time_ns, m.log_time_ns))
                p, q = full.msg.pose.position, full.msg.pose.orientation
                T = se3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]), np.array([p.x, p.y, p.z]))
                w.write_pose(GT_TOPIC, T, m.log_time_ns, "tool_nowhere")
            else:
                w.write_raw(m.topic, m.type, bytes(m.msg), m.log_time_ns, m.publish_time_ns)
    with pytest.raises(LogError) as err:
        evaluate(folder, out, None, d / "r_bad", config=CFG)
    assert "tool_nowhere" in str(err.value) and "\n" not in str(err.value)
