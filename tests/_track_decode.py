"""track.mcap decoded with independent readers: the ``mcap`` library's reader and ``rosbags``'
CDR deserialiser, built from each schema's own text (tests of the track's topics)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation


def decode_track(path: Path) -> list[tuple[str, str, int, object]]:
    """(topic, schema name, log time, message) of every message of an MCAP file."""
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.EMPTY)
    out = []
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema in reader.get_summary().schemas.values():
            assert schema.encoding == "ros2msg"
            store.register(typesys.get_types_from_msg(schema.data.decode(), schema.name))
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "cdr"
            out.append((channel.topic, schema.name, message.log_time, store.deserialize_cdr(message.data, schema.name)))
    return out


def pose_of(t, q) -> np.ndarray:
    """(4, 4) pose from a decoded translation / position and quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T
