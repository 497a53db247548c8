"""rosbag2's own compression (per message, per file), on bags written by an independent writer.

The bags are written with the ``rosbags`` library (its rosbag2 writer with the MCAP storage
plugin, the ``ros2 bag record --compression-mode message|file --compression-format zstd``
layout) from the messages of the shipped cube sample log; reading them must give the sample
log's messages byte for byte, and the same pose track.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from mvtop_cli.config import load_config
from mvtop_cli.errors import LogError
from mvtop_cli.io.mcap_reader import McapLog, read_summary
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate

rosbag2 = pytest.importorskip("rosbags.rosbag2")
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_logs" / "cube.mcap"
CONFIG = ROOT / "configs" / "cube.yaml"


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with McapLog(path) as log:
        return [(m.topic, m.log_time_ns, bytes(m.msg)) for m in log.messages(decode=False)]


def write_bag(src: Path, dst: Path, mode: CompressionMode | None) -> Path:
    """``src``'s messages as a rosbag2 MCAP bag folder written by rosbags."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    writer = rosbag2.Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    if mode is not None:
        writer.set_compression(mode, CompressionFormat.ZSTD)
    with McapLog(src) as log, writer:
        conns = {t.name: writer.add_connection(t.name, t.type, typestore=store) for t in log.summary().topics}
        for m in log.messages(decode=False):
            writer.write(conns[m.topic], m.log_time_ns, bytes(m.msg))
    return dst


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bags")
    return {
        "plain": write_bag(SAMPLE, d / "plain", None),
        "message": write_bag(SAMPLE, d / "message", CompressionMode.MESSAGE),
        "file": write_bag(SAMPLE, d / "file", CompressionMode.FILE),
    }


def test_the_bags_are_what_they_claim(bags):
    meta = {k: yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            for k, p in bags.items()}
    assert (meta["message"]["compression_mode"], meta["message"]["compression_format"]) == ("message", "zstd")
    assert (meta["file"]["compression_mode"], meta["file"]["compression_format"]) == ("file", "zstd")
    assert meta["file"]["relative_file_paths"][0].endswith(".mcap.zstd")
    # per-message compression: the stored message data are zstd frames, not CDR
    from mcap.reader import make_reader

    with open(bags["message"] / meta["message"]["relative_file_paths"][0], "rb") as fh:
        datas = [m.data for _s, _c, m in make_reader(fh).iter_messages()]
    assert datas and all(d[:4] == b"\x28\xb5\x2f\xfd" for d in datas)


@pytest.mark.parametrize("kind,expected", [("plain", None), ("message", "zstd per message"), ("file", "zstd per file")])
def test_compressed_bags_read_as_the_plain_log(bags, kind, expected):
    original = _messages(SAMPLE)
    assert _messages(bags[kind]) == original
    s, s0 = read_summary(bags[kind]), read_summary(SAMPLE)
    assert s.bag_compression == expected
    assert [(t.name, t.message_count) for t in s.topics] == [(t.name, t.message_count) for t in s0.topics]


def test_file_compressed_bag_leaves_no_temporary_copy(bags):
    log = McapLog(bags["file"])
    tmp = log._tmpdir
    assert tmp is not None and tmp.is_dir() and any(tmp.iterdir())
    log.close()
    assert not tmp.exists()


def test_message_compressed_file_without_metadata_is_recognised(bags, tmp_path):
    (f,) = list(bags["message"].glob("*.mcap"))
    lone = tmp_path / "lone.mcap"
    shutil.copy(f, lone)
    assert read_summary(lone).bag_compression == "zstd per message"
    with McapLog(lone) as log:
        tf = next(log.messages("/tf"))
    assert len(tf.msg.transforms) >= 1


def test_corrupt_compressed_message_names_topic_and_time(bags, tmp_path):
    store = get_typestore(Stores.ROS2_HUMBLE)
    dst = tmp_path / "bad"
    writer = rosbag2.Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        c = writer.add_connection("/contact", "std_msgs/msg/Bool", typestore=store)
        writer.write(c, 5_000, b"\x28\xb5\x2f\xfd" + b"\x00" * 12)  # a zstd magic, then garbage
    with McapLog(dst) as log, pytest.raises(LogError) as err:
        list(log.messages("/contact"))
    msg = str(err.value)
    assert "'/contact'" in msg and "5000 ns" in msg and "does not decompress" in msg and "\n" not in msg


def test_corrupt_file_compressed_bag_is_one_clear_error(bags, tmp_path):
    dst = tmp_path / "bad_file"
    shutil.copytree(bags["file"], dst)
    (f,) = list(dst.glob("*.zstd"))
    f.write_bytes(f.read_bytes()[:1000])
    with pytest.raises(LogError) as err:
        McapLog(dst)
    assert str(err.value).startswith(str(f)) and "\n" not in str(err.value)


def test_track_from_message_compressed_bag_equals_the_plain_one(bags, tmp_path):
    cfg = load_config(CONFIG)
    opts = EstimateOptions(num_particles=40, seed=0, max_frames=2)
    estimate(bags["plain"], cfg, tmp_path / "plain", opts)
    estimate(bags["message"], cfg, tmp_path / "message", opts)
    plain = (tmp_path / "plain" / "track.csv").read_text()
    assert plain.count("\n") == 3
    assert (tmp_path / "message" / "track.csv").read_text() == plain
