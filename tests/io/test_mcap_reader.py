"""MCAP reader: real rosbag2 files, bag folders, unindexed files, time windows, and bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from _io_scene import MS, REAL, T0, write_scene
from _real_data import needs_real_data
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter

from mvtop_cli.errors import LogError
from mvtop_cli.io import ros2_msgs as rm
from mvtop_cli.io.mcap_reader import McapLog, bag_files, read_summary
from mvtop_cli.io.mcap_writer import LogWriter

CPP = REAL / "rosbag2_cpp_test_rosbag2_cpp_bags"
MULTI = REAL / "rosbag2_py_test_resources_mcap_reindex_test_bags_multiple_files"

# (path, {topic: (type, count)}, start_ns, end_ns, compression): established independently
# with mcap's StreamReader (decompressing every chunk and counting Message records).
REAL_LOGS = [
    (CPP / "only_services.mcap",
     {"/add_two_ints/_service_event": ("example_interfaces/srv/AddTwoInts_Event", 12)},
     1697521953726475197, 1697521956226579212, ("none",)),
    (CPP / "only_topics.mcap",
     {"/events/write_split": ("rosbag2_interfaces/msg/WriteSplitEvent", 0),
      "/parameter_events": ("rcl_interfaces/msg/ParameterEvent", 7),
      "/rosout": ("rcl_interfaces/msg/Log", 0)},
     1697521620031724098, 1697521620038262023, ("none",)),
    (CPP / "topics_and_services.mcap",
     {"/add_two_ints/_service_event": ("example_interfaces/srv/AddTwoInts_Event", 6),
      "/add_two_ints2/_service_event": ("example_interfaces/srv/AddTwoInts_Event", 0),
      "/events/write_split": ("rosbag2_interfaces/msg/WriteSplitEvent", 0),
      "/parameter_events": ("rcl_interfaces/msg/ParameterEvent", 7),
      "/rosout": ("rcl_interfaces/msg/Log", 0)},
     1697522263121459207, 1697522264629347866, ("none",)),
    (REAL / "rosbag2_py_test_resources_mcap_convert_b",
     {"a_empty": ("test_msgs/msg/Empty", 25), "c_strings": ("test_msgs/msg/Strings", 50)},
     0, 222000000, ("none",)),
    (MULTI,
     {"/chatter": ("std_msgs/msg/String", 1324 + 1324 + 529)},
     1616653333034080451, 1616653339386193357, ("zstd",)),
    (MULTI / "multiple_files_1.mcap",
     {"/chatter": ("std_msgs/msg/String", 1324)},
     1616653335682137991, 1616653338328104450, ("zstd",)),
    (REAL / "rosbag2_py_test_resources_mcap_talker",
     {"/parameter_events": ("rcl_interfaces/msg/ParameterEvent", 0),
      "/rosout": ("rcl_interfaces/msg/Log", 10), "/topic": ("std_msgs/msg/String", 10)},
     1585866235112411371, 1585866239643508139, ("zstd",)),
    (REAL / "rosbag2_tests_resources_mcap_cdr_test",
     {"/array_topic": ("test_msgs/msg/Arrays", 4), "/test_topic": ("test_msgs/msg/BasicTypes", 3)},
     1586406456763032325, 1586406456914169506, ("none",)),
    (REAL / "rosbag2_transport_test_resources_mcap_test_bag_for_seek",
     {"topic1": ("test_msgs/BasicTypes", 5)}, 1000000000, 1400000000, ("none",)),
]


@needs_real_data
@pytest.mark.parametrize("path,topics,start,end,compression", REAL_LOGS, ids=lambda v: getattr(v, "name", None))
def test_real_rosbag2_logs(path, topics, start, end, compression):
    with McapLog(path) as log:
        s = log.summary()
        assert s.profile == "ros2" and s.indexed
        assert {t.name: (t.type, t.message_count) for t in s.topics} == topics
        assert (s.start_ns, s.end_ns, s.compression) == (start, end, compression)
        assert s.message_count == sum(c for _t, c in topics.values())
        assert all(t.schema_encoding == "ros2msg" and t.message_encoding == "cdr" for t in s.topics)
        # reading every message (undecoded) gives the same counts, in log-time order
        times, counts = [], {}
        for m in log.messages(decode=False):
            times.append(m.log_time_ns)
            counts[m.topic] = counts.get(m.topic, 0) + 1
        assert counts == {k: c for k, (_t, c) in topics.items() if c}
        assert times == sorted(times) and (times[0], times[-1]) == (start, end)


@needs_real_data
@pytest.mark.parametrize("folder", [p.parent for p in REAL.glob("*/metadata.yaml")], ids=lambda p: p.name)
def test_bag_folders_agree_with_their_metadata_yaml(folder):
    info = yaml.safe_load((folder / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    s = read_summary(folder)
    expected = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert {t.name: t.message_count for t in s.topics} == expected
    assert s.message_count == info["message_count"]
    assert s.start_ns == info["starting_time"]["nanoseconds_since_epoch"]
    assert s.end_ns - s.start_ns == info["duration"]["nanoseconds"]


@needs_real_data
def test_split_bag_reads_as_one_log_in_time_order():
    assert [p.name for p in bag_files(MULTI)] == [f"multiple_files_{i}.mcap" for i in range(3)]
    with McapLog(MULTI) as log:
        assert len(log.files) == 3
        msgs = list(log.messages("/chatter"))
        assert len(msgs) == 3177 and all(m.msg.data == "test" for m in msgs)
        times = [m.log_time_ns for m in msgs]
        assert times == sorted(times)
        # the file boundary: last message of file 0, first of file 1
        assert 1616653335680263369 in times and times[times.index(1616653335680263369) + 1] == 1616653335682137991
        # an inclusive time window spanning files 0 and 1 (count checked against mcap's reader)
        window = list(log.messages("/chatter", start_ns=1616653335000000000, end_ns=1616653336000000000, decode=False))
    ref = 0
    for name in ("multiple_files_0.mcap", "multiple_files_1.mcap"):
        with open(MULTI / name, "rb") as fh:
            ref += sum(
                1 for _ in make_reader(fh).iter_messages(starting_at=1616653335000000000, ending_at=1616653336000000000)
            )
    assert len(window) == ref == 500
    rate = read_summary(MULTI).topic("/chatter").rate_hz
    assert rate == pytest.approx(500.0, rel=1e-3)


@needs_real_data
def test_real_messages_decode():
    with McapLog(REAL / "rosbag2_py_test_resources_mcap_talker") as log:
        topic = [m.msg.data for m in log.messages("/topic")]
        rosout = next(iter(log.messages("/rosout")))
    assert topic == [f"Hello, world! {i}" for i in range(10)]
    assert rosout.type == "rcl_interfaces/msg/Log" and rosout.msg.name == "minimal_publisher"
    with McapLog(REAL / "rosbag2_tests_resources_mcap_cdr_test") as log:
        basic = next(iter(log.messages("/test_topic")))
    assert basic.msg.int32_value == 123


@needs_real_data
def test_service_event_schemas_fail_to_decode_with_a_clear_error():
    # rosbag2 records service events with the .srv text (request --- response) as
    # schema; mcap_ros2 cannot parse that. Reading them undecoded still works.
    path = CPP / "only_services.mcap"
    with McapLog(path) as log:
        assert sum(1 for _ in log.messages(decode=False)) == 12
        with pytest.raises(
            LogError,
            match=r"only_services\.mcap: cannot parse the ros2msg schema 'example_interfaces/srv/AddTwoInts_Event' "
            r"of topic '/add_two_ints/_service_event'",
        ):
            log.messages()
    with McapLog(CPP / "topics_and_services.mcap") as log:  # other topics of the same file decode
        assert len(list(log.messages("/parameter_events"))) == 7


# --- synthetic logs --------------------------------------------------------------------------


def test_out_of_order_writes_come_back_in_log_time_order(tmp_path):
    path = tmp_path / "ooo.mcap"
    times = [T0 + i * MS for i in np.random.default_rng(5).permutation(200)]
    with LogWriter(path, chunk_size=512) as w:  # many small chunks that overlap in time
        for i, t in enumerate(times):
            w.write_bool("/a" if i % 2 else "/b", bool(i % 3), t)
    with McapLog(path) as log:
        got = [m.log_time_ns for m in log.messages()]
        assert got == sorted(times)
        assert [m.log_time_ns for m in log.messages("/a")] == sorted(times[1::2])
        window = [m.log_time_ns for m in log.messages(start_ns=T0 + 10 * MS, end_ns=T0 + 19 * MS)]
        assert window == [T0 + i * MS for i in range(10, 20)]  # inclusive at both ends
        s = log.summary()
        assert s.topic("/a").message_count == 100 and s.topic("/b").message_count == 100
        assert (s.topic("/b").first_ns, s.topic("/b").last_ns) == (min(times[0::2]), max(times[0::2]))
        assert (s.start_ns, s.end_ns) == (T0, T0 + 199 * MS)


def _plain_mcap(path, chunked: bool, summary: bool):
    """A ros2 MCAP written with mcap's low-level writer: unchunked and/or without summary."""
    with open(path, "wb") as fh:
        kwargs = {} if summary else dict(
            index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
            use_statistics=False, use_summary_offsets=False,
        )
        w = McapWriter(fh, use_chunking=chunked, compression=CompressionType.ZSTD, **kwargs)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(rm.BOOL, "ros2msg", rm.definition(rm.BOOL).encode())
        cid = w.register_channel("/contact", "cdr", sid)
        for i in (3, 1, 2, 0):
            w.add_message(cid, log_time=T0 + i, data=b"\x00\x01\x00\x00" + bytes([i % 2]), publish_time=T0 + i)
        w.finish()


@pytest.mark.parametrize("chunked,summary,indexed,compression", [
    (False, True, False, ("unchunked",)),
    (False, False, False, ("unchunked",)),
    (True, False, False, ("zstd",)),
])
def test_files_without_index_are_scanned(tmp_path, chunked, summary, indexed, compression):
    path = tmp_path / "plain.mcap"
    _plain_mcap(path, chunked, summary)
    with McapLog(path) as log:
        s = log.summary()
        assert (s.indexed, s.compression) == (indexed, compression)
        assert s.topic("/contact").message_count == 4 and (s.start_ns, s.end_ns) == (T0, T0 + 3)
        msgs = list(log.messages("/contact"))
    assert [m.log_time_ns for m in msgs] == [T0, T0 + 1, T0 + 2, T0 + 3]
    assert [m.msg.data for m in msgs] == [False, True, False, True]


# --- bad inputs --------------------------------------------------------------------------------


def test_not_an_mcap_file(tmp_path):
    path = tmp_path / "notes.mcap"
    path.write_text("hello world, this is text")
    with pytest.raises(
        LogError,
        match=r"notes\.mcap: not an MCAP file \(starts with b'hello wo', expected the MCAP magic b'\\x89MCAP0\\r\\n'\)",
    ):
        McapLog(path)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(LogError, match=r"empty\.mcap: not an MCAP file \(starts with b''"):
        McapLog(tmp_path / "empty.mcap")
    with pytest.raises(
        LogError, match=r"missing\.mcap: no such file or folder \(expected an \.mcap file or a rosbag2 bag folder\)"
    ):
        McapLog(tmp_path / "missing.mcap")
    (tmp_path / "bag").mkdir()
    with pytest.raises(LogError, match=r"bag: folder holds no \.mcap files"):
        McapLog(tmp_path / "bag")


def test_bag_metadata_problems(tmp_path):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: mcap\n  relative_file_paths: [bag_0.mcap]\n"
    )
    with pytest.raises(LogError, match=r"metadata\.yaml: lists files that are not in the folder: bag_0\.mcap"):
        McapLog(bag)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n")
    with pytest.raises(LogError, match=r"bag storage is 'sqlite3' \(expected 'mcap'\)"):
        McapLog(bag)


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("small") / "small.mcap"
    write_scene(path, "zstd")
    return path


def test_truncated_files_raise_naming_file_and_expectation(small_log, tmp_path):
    data = small_log.read_bytes()
    size = len(data)
    for cut in [4, 8, 12, 30, 200, size // 3, size // 2, size - 40, size - 1]:
        path = tmp_path / f"cut_{cut}.mcap"
        path.write_bytes(data[:cut])
        with pytest.raises(LogError) as info:
            McapLog(path)
        msg = str(info.value)
        assert msg.startswith(f"{path}: ") and "\n" not in msg
        if cut < 8:
            assert "not an MCAP file" in msg
        else:
            assert "truncated" in msg and ("expected" in msg or "needs" in msg)


def test_truncated_file_reads_up_to_the_cut_when_allowed(small_log, tmp_path):
    data = small_log.read_bytes()
    with McapLog(small_log) as log:
        total = log.summary().message_count
    for frac in (0.3, 0.6, 0.95):
        cut = int(len(data) * frac)
        path = tmp_path / f"cut_{cut}.mcap"
        path.write_bytes(data[:cut])
        with McapLog(path, allow_truncated=True) as log:
            s = log.summary()
            assert not s.indexed and s.truncated_at is not None and s.truncated_at[0] == path
            assert 0 < s.message_count <= total
            msgs = list(log.messages())  # every complete message decodes
            assert len(msgs) == s.message_count
            assert [m.log_time_ns for m in msgs] == sorted(m.log_time_ns for m in msgs)
    path = tmp_path / "cut_12.mcap"
    path.write_bytes(data[:12])
    with pytest.raises(LogError, match="truncated"):
        McapLog(path, allow_truncated=True)  # not even a header


def _first_chunk(path):
    with open(path, "rb") as fh:
        return make_reader(fh).get_summary().chunk_indexes[0]


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_corrupt_chunk_raises_naming_file_and_offset(tmp_path, compression):
    path = tmp_path / f"corrupt_{compression}.mcap"
    write_scene(path, compression)
    ci = _first_chunk(path)
    data = bytearray(path.read_bytes())
    middle = ci.chunk_start_offset + ci.chunk_length // 2
    data[middle : middle + 64] = bytes(64)
    data[middle + 64 : middle + 96] = b"\xff" * 32
    path.write_bytes(bytes(data))
    with McapLog(path) as log:  # the summary is intact
        with pytest.raises(LogError) as info:
            list(log.messages())
    msg = str(info.value)
    assert msg.startswith(f"{path}: corrupt chunk at byte {ci.chunk_start_offset} (")
    assert (
        f"expected {compression if compression != 'none' else 'uncompressed'} "
        f"data of {ci.uncompressed_size} bytes" in msg
    )


def test_missing_topic_names_file_and_topics(small_log):
    with McapLog(small_log) as log:
        with pytest.raises(
            LogError, match=r"small\.mcap: topic '/camera/image' not found \(topics: /cameras/front/camera_info, "
        ):
            log.messages(["/camera/image", "/tf"])
        with pytest.raises(
            LogError,
            match=r"small\.mcap: topic '/wrist/image' not found \(expected sensor_msgs/msg/Image messages; topics: ",
        ):
            log.require_topics({"/tf": rm.TF_MESSAGE, "/wrist/image": rm.IMAGE})
        with pytest.raises(
            LogError, match=r"topic '/contact' has type 'std_msgs/msg/Bool' \(expected sensor_msgs/msg/Image\)"
        ):
            log.require_topics({"/contact": rm.IMAGE})
        log.require_topics({"/tf": "tf2_msgs/TFMessage", "/contact": None})  # short type names are fine
        with pytest.raises(LogError, match=r"topic '/nope' not found"):
            log.summary().topic("/nope")


def test_non_ros2msg_schema_is_rejected(tmp_path):
    path = tmp_path / "json.mcap"
    with open(path, "wb") as fh:
        w = McapWriter(fh)
        w.start(profile="", library="test")
        sid = w.register_schema("Pose", "jsonschema", b"{}")
        cid = w.register_channel("/pose", "json", sid)
        w.add_message(cid, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    with McapLog(path) as log:
        assert log.summary().topic("/pose").schema_encoding == "jsonschema"
        with pytest.raises(
            LogError,
            match=r"json\.mcap: topic '/pose' has schema encoding 'jsonschema' and message encoding 'json' "
            r"\(expected 'ros2msg' schemas with 'cdr' messages",
        ):
            log.messages("/pose")


def test_message_that_fails_to_decode_names_topic_and_time(tmp_path):
    path = tmp_path / "garbage.mcap"
    with LogWriter(path) as w:
        w.write_bool("/contact", True, T0)
        w.write_raw("/cameras/front/image", rm.IMAGE, b"\x00\x01\x00\x00\x05\x00", T0 + 5)
    with McapLog(path) as log:
        it = log.messages()
        assert next(it).topic == "/contact"
        with pytest.raises(
            LogError,
            match=r"garbage\.mcap: message on topic '/cameras/front/image' at log time 1700000000000000005 ns "
            r"does not decode as sensor_msgs/msg/Image \(",
        ):
            next(it)


def test_undecoded_messages_are_raw_cdr_bytes(small_log):
    with McapLog(small_log) as log:
        raw = next(iter(log.messages("/contact", decode=False)))
    assert raw.type == rm.BOOL and isinstance(raw.msg, bytes)
    assert raw.msg == b"\x00\x01\x00\x00\x00"  # CDR little-endian header, then False
