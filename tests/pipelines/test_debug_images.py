"""``mvtop estimate --debug-images``: the observed and rendered masks of every sensor in track.mcap,
decoded with independent readers (the ``mcap`` reader with ``rosbags``' CDR deserialiser built
from each schema's own text, and mcap_ros2's decoder): every schema parses, every image's frame
connects to ``world`` through the file's /tf, and each pair of masks has the IoU the estimator
scored for that sensor at the estimate. The flag changes nothing else in the outputs."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from _track_decode import decode_track, pose_of
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from mvtop_cli.config import load_config
from mvtop_cli.estimator import Estimator
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.checkpoint import EstimateInterrupted
from mvtop_cli.pipelines.estimate import EstimateOptions, apply_options, estimate, log_topics, sensor_topics

pytest.importorskip("rosbags.typesys")

ROOT = Path(__file__).resolve().parents[2]
LOG = ROOT / "sample_logs" / "cube.mcap"
CONFIG = ROOT / "configs" / "cube.yaml"
OPTIONS = EstimateOptions(num_particles=30, seed=0, max_frames=2)
SENSORS = {"front": "front_optical", "side": "side_optical", "left": "tactile_left_optical",
           "right": "tactile_right_optical"}


def stamp(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def read_all(path: Path) -> list[tuple[str, str, object]]:
    """(topic, schema name, message) of every message, decoded by rosbags from the file's schemas."""
    return [(topic, schema, msg) for topic, schema, _time, msg in decode_track(path)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """The same estimate without and with --debug-images."""
    cfg = load_config(CONFIG)
    plain, debug = tmp_path_factory.mktemp("plain"), tmp_path_factory.mktemp("debug")
    estimate(LOG, cfg, plain, OPTIONS)
    estimate(LOG, cfg, debug, EstimateOptions(**{**vars(OPTIONS), "debug_images": True}))
    return plain, debug


@pytest.fixture(scope="module")
def scored() -> list[tuple[int, dict[str, float], dict[str, float]]]:
    """(stamp, per-sensor IoU at the estimate, per-sensor observed area outside the ROI window
    [image pixels]) of the run's frames, from the estimator itself."""
    cfg = apply_options(load_config(CONFIG), OPTIONS)
    out = []
    with McapLog(LOG) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        est = Estimator.from_config(cfg, lambda frame, t: reader.tf.lookup(cfg.frames.world, frame, t))
        for frame in reader:
            r = est.step(frame)
            obs = est.last_likelihood.observation
            out.append((r.stamp_ns, r.sensor_iou, {n: obs.outside[n] / obs.rois[n].scale**2 for n in obs.sensors}))
            if len(out) == OPTIONS.max_frames:
                break
    return out


def test_the_flag_changes_nothing_else(runs):
    plain, debug = runs
    assert (plain / "track.csv").read_bytes() == (debug / "track.csv").read_bytes()
    msgs = {(t, s, repr(m)) for t, s, m in read_all(plain / "track.mcap")}
    assert msgs <= {(t, s, repr(m)) for t, s, m in read_all(debug / "track.mcap")}


def test_every_schema_parses_with_two_decoders_and_every_sensor_has_both_masks(runs):
    msgs = read_all(runs[1] / "track.mcap")
    debug = {(t, s) for t, s, _m in msgs if t.startswith("/mvtop/debug/")}
    assert debug == {(f"/mvtop/debug/{n}/{k}", "sensor_msgs/msg/Image") for n in SENSORS
                     for k in ("observed", "rendered")} | {(f"/mvtop/debug/{n}/camera_info",
                                                            "sensor_msgs/msg/CameraInfo") for n in SENSORS}
    with open(runs[1] / "track.mcap", "rb") as fh:
        n = sum(1 for _ in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert n == len(msgs)
    stamps = [int(line.split(",")[1]) for line in (runs[1] / "track.csv").read_text().splitlines()[1:]]
    for t, _s, m in msgs:
        if t.startswith("/mvtop/debug/"):
            name = t.split("/")[3]
            assert m.header.frame_id == SENSORS[name] and stamp(m.header) in stamps
    per_stamp = [sum(1 for t, _s, m in msgs if t.endswith("/observed") and stamp(m.header) == st) for st in stamps]
    assert per_stamp == [len(SENSORS)] * len(stamps)


def test_every_image_frame_connects_to_world_at_its_stamp(runs):
    msgs = read_all(runs[1] / "track.mcap")
    tf = {}
    for t, _s, m in msgs:
        if t == "/tf":
            for tr in m.transforms:
                T = pose_of(tr.transform.translation, tr.transform.rotation)
                tf[(tr.child_frame_id, stamp(tr.header))] = (tr.header.frame_id, T)
    cfg = load_config(CONFIG)
    with McapLog(LOG) as log:
        frames = {f.stamp_ns: f for _, f in zip(range(2), FrameReader(log, sensor_topics(cfg), log_topics(cfg)))}
    for t, _s, m in msgs:
        if t.startswith("/mvtop/debug/"):
            parent, T = tf[(m.header.frame_id, stamp(m.header))]  # KeyError: not connected at this stamp
            assert parent == "world"
            img = frames[stamp(m.header)].image(t.split("/")[3])
            np.testing.assert_allclose(T, img.T_world_sensor, atol=1e-9)


def test_masks_are_full_size_and_their_iou_is_the_scored_one(runs, scored):
    msgs = read_all(runs[1] / "track.mcap")
    info = {(t.split("/")[3], stamp(m.header)): m for t, _s, m in msgs if t.endswith("/camera_info")}
    images = {}
    for t, _s, m in msgs:
        if t.endswith("/observed") or t.endswith("/rendered"):
            name = t.split("/")[3]
            ci = info[(name, stamp(m.header))]
            assert (m.encoding, m.height, m.width, m.step) == ("mono8", ci.height, ci.width, ci.width)
            a = np.asarray(m.data, dtype=np.uint8).reshape(m.height, m.width)
            assert set(np.unique(a)) <= {0, 255}
            images[(name, stamp(m.header), t.split("/")[4])] = a > 0
    checked = 0
    for st, ious, outside in scored:
        assert set(ious) == set(SENSORS)
        for name, iou in ious.items():
            o, r = images[(name, st, "observed")], images[(name, st, "rendered")]
            assert o.any() and r.any()
            if name in ("front", "side"):
                assert outside[name] == 0  # a camera's mask is made inside its window
            # every ROI pixel stands for the same number of image pixels, so the IoU is the same once
            # the observed area outside the window (tactile: not drawn) joins the union
            assert (o & r).sum() / ((o | r).sum() + outside[name]) == pytest.approx(iou, abs=1e-9), (name, st)
            checked += 1
    assert checked == len(SENSORS) * OPTIONS.max_frames


def test_a_checkpoint_of_the_other_setting_is_refused(tmp_path):
    cfg = load_config(CONFIG)

    def stop_at_1(done: int, total: int) -> None:
        if done == 1:
            raise KeyboardInterrupt

    with pytest.raises(EstimateInterrupted):
        estimate(LOG, cfg, tmp_path, OPTIONS, progress=stop_at_1)
    with pytest.raises(Exception, match=r"option debug_images differs \(false in the checkpoint, true now\)"):
        estimate(LOG, cfg, tmp_path, EstimateOptions(**{**vars(OPTIONS), "debug_images": True}), resume=True)


def test_cli_debug_images_takes_one_log(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mvtop_cli", "estimate", str(LOG), str(LOG), "--config", str(CONFIG),
                           "--out", str(tmp_path / "out"), "--debug-images"], capture_output=True, text=True)
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines()[-1].endswith("--debug-images works with a single LOG (run it on the log "
                                                         "whose masks you want to see)")
    assert not (tmp_path / "out").exists()


def test_the_foxglove_layout_names_topics_of_the_track(runs):
    """docs/foxglove-layout.json shows topics a --debug-images track of a sample log has."""
    import json

    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    named = set()
    for panel in layout["configById"].values():
        named |= set(panel.get("topics", {}))
        named |= {v for k, v in panel.get("imageMode", {}).items() if k.endswith("Topic")}
        named |= {p["value"].split(".")[0] for p in panel.get("paths", [])}
    assert {"/mvtop/debug/front/observed", "/mvtop/debug/left/rendered", "/mvtop/debug/left/camera_info"} <= named
    assert named <= {t for t, _s, _m in read_all(runs[1] / "track.mcap")}


def test_soft_camera_evidence_is_drawn_as_its_probability(tmp_path):
    """With ``masking.camera_evidence: colour`` the run's frames say so (``mask_mode``) and a
    camera's observed debug image is its per-pixel object probability in 255 levels: undecided
    pixels show as grey, not as a cut mask; the tactile masks stay 0 / 255."""
    cfg = load_config(CONFIG)
    cfg = replace(cfg, masking=replace(cfg.masking, camera_evidence="colour"))
    estimate(LOG, cfg, tmp_path, EstimateOptions(**{**vars(OPTIONS), "debug_images": True}))
    rows = (tmp_path / "track.csv").read_text().splitlines()
    assert all(row.split(",")[23] == "colour" for row in rows[1:]) and rows[0].split(",")[23] == "mask_mode"
    observed = {t: m for t, _s, m in read_all(tmp_path / "track.mcap") if t.endswith("/observed")}
    front = np.frombuffer(observed["/mvtop/debug/front/observed"].data, np.uint8)
    assert np.any((front > 0) & (front < 255)) and front.max() > 200
    left = np.frombuffer(observed["/mvtop/debug/left/observed"].data, np.uint8)
    assert set(np.unique(left)) <= {0, 255}


def test_a_corrected_camera_is_drawn_as_the_run_used_it(tmp_path):
    """The cube sample with its front camera recorded turned 2 deg (scripts/perturb_extrinsics.py):
    the run corrects it (estimator/extrinsics.py), and --debug-images draws its masks in the
    camera as corrected, whose /tf pose in track.mcap is the log-as-recorded's to within 0.1 deg,
    while the side camera's is the log's to the bit."""
    from mvtop_cli.geometry import se3

    turned = tmp_path / "turned.mcap"
    made = subprocess.run([sys.executable, str(ROOT / "scripts" / "perturb_extrinsics.py"), str(LOG), str(turned),
                           "front_optical", "2"], capture_output=True, text=True, timeout=600)
    assert made.returncode == 0, made.stderr
    out = tmp_path / "debug"
    cfg = load_config(CONFIG)
    estimate(turned, cfg, out, EstimateOptions(**{**vars(OPTIONS), "max_frames": 1, "debug_images": True}))
    with McapLog(LOG) as log:
        recorded = next(iter(FrameReader(log, sensor_topics(cfg), log_topics(cfg))))
    seen = {}
    for t, _s, m in read_all(out / "track.mcap"):
        if t == "/tf":
            for tr in m.transforms:
                seen[tr.child_frame_id] = pose_of(tr.transform.translation, tr.transform.rotation)
    front = se3.invert(recorded.cameras["front"].T_world_sensor) @ seen["front_optical"]
    assert np.degrees(se3.rotation_angle(front[:3, :3])) < 0.1
    np.testing.assert_allclose(seen["side_optical"], recorded.cameras["side"].T_world_sensor, atol=1e-9)
