"""track.mcap opens by itself: decoded with independent readers (the ``mcap`` library's reader
with ``rosbags``' CDR deserialiser and mcap_ros2's decoder), every schema parses, every frame
of every message connects to ``world`` through the file's own /tf, and the model is the CAD mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _track_decode import decode_track, pose_of
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from mvtop_cli.config import load_config
from mvtop_cli.io.meshes import load_mesh
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

pytest.importorskip("rosbags.typesys")

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def track(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("track")
    estimate(ROOT / "sample_logs" / "cube.mcap", load_config(ROOT / "configs" / "cube.yaml"), out,
             EstimateOptions(num_particles=40, seed=0, max_frames=3))
    return out / "track.mcap"


def test_every_message_decodes_with_independent_readers(track):
    msgs = decode_track(track)
    topics = {t for t, *_ in msgs}
    assert topics == {"/tf", "/mvtop/object_model", "/mvtop/object_pose", "/mvtop/object_pose_ee", "/mvtop/particles"}
    # mcap_ros2 decodes the same bytes too
    with open(track, "rb") as fh:
        n = sum(1 for _ in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert n == len(msgs)


def test_every_frame_connects_to_world_at_every_stamp(track):
    msgs = decode_track(track)
    tf: dict[tuple[str, int], tuple[str, np.ndarray]] = {}  # (child, stamp) -> (parent, T_parent_child)
    for topic, _s, _t, m in msgs:
        if topic == "/tf":
            for tr in m.transforms:
                stamp = tr.header.stamp.sec * 10**9 + tr.header.stamp.nanosec
                T = pose_of(tr.transform.translation, tr.transform.rotation)
                tf[(tr.child_frame_id, stamp)] = (tr.header.frame_id, T)

    def in_world(frame: str, stamp: int) -> np.ndarray:
        T = np.eye(4)
        while frame != "world":
            parent, T_pc = tf[(frame, stamp)]  # KeyError: the frame does not connect at this stamp
            T, frame = T_pc @ T, parent
        return T

    poses = [(m.header.frame_id, m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m.pose)
             for topic, _s, _t, m in msgs if topic in ("/mvtop/object_pose", "/mvtop/object_pose_ee")]
    stamps = sorted({s for _f, s, _p in poses})
    assert len(stamps) == 3 and {f for f, *_ in poses} == {"world", "ee"}
    for stamp in stamps:
        world, ee = ([pose_of(p.position, p.orientation) for f, s, p in poses if s == stamp and f == fr][0]
                     for fr in ("world", "ee"))
        np.testing.assert_allclose(in_world("object_estimate", stamp), world, atol=1e-9)
        np.testing.assert_allclose(in_world("ee", stamp) @ ee, world, atol=1e-9)
    for topic, _s, _t, m in msgs:  # every other message is in a frame the file's TF knows
        if topic != "/tf":
            in_world(m.header.frame_id, stamps[0] if topic == "/mvtop/object_model" else
                     m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)


def test_model_marker_is_the_cad_mesh(track):
    (marker,) = [m for topic, _s, _t, m in decode_track(track) if topic == "/mvtop/object_model"]
    mesh = load_mesh(ROOT / "configs" / "meshes" / "cube.obj", "m")
    assert marker.type == 11 and marker.frame_locked and marker.header.frame_id == "object_estimate"
    pts = np.array([[p.x, p.y, p.z] for p in marker.points])
    np.testing.assert_allclose(pts.reshape(-1, 3, 3), np.asarray(mesh.vertices)[np.asarray(mesh.faces)], atol=1e-12)
    assert marker.color.a > 0.5 and marker.lifetime.sec == 0 and marker.lifetime.nanosec == 0


def test_tf_has_world_to_ee_and_world_to_object_estimate(track):
    pairs = {(tr.header.frame_id, tr.child_frame_id) for topic, _s, _t, m in decode_track(track) if topic == "/tf"
             for tr in m.transforms}
    assert pairs == {("world", "ee"), ("world", "object_estimate")}
