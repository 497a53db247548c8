"""Streaming reader for ROS 2 MCAP logs (rosbag2 output): one .mcap file, or a bag folder as one log.

A log is never loaded whole. When a file has a summary section, the chunk indexes and
message indexes tell which chunks hold which topics and when; without one (a recorder
that was killed, a writer that skips the summary) the file is scanned once, linearly,
to build the same index in memory (offsets and times only). Messages are then read
chunk by chunk and merged into log-time order with a heap, so only the chunks that
overlap in time are in memory at once. rosbag2's own compression is undone too: per
message (each message's data a zstd frame) as each message is read, per file
(``NAME.mcap.zstd``) by streaming the file into a temporary folder that ``close()``
removes (bag_compression.py).

Every failure is a LogError with one line naming the file and what was expected;
third-party exceptions are wrapped here, once.
"""

from __future__ import annotations

import contextlib
import heapq
import io
import re
import shutil
import struct
import tempfile
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Footer, Header, Schema, Statistics

from ..errors import LogError
from .bag_compression import decompress_file, decompress_message, file_compression, message_compression
from .ros2_msgs import MESSAGE_TYPES, normalize_type, schema_mismatch

MAGIC = b"\x89MCAP0\r\n"
_FOOTER_RECORD_SIZE = 1 + 8 + 20  # opcode, length, (summary_start, summary_offset_start, crc)
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
MAX_TIME_NS = 2**63 - 1  # times are int64 nanoseconds inside mvtop (MCAP allows uint64)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a log: ``type`` is the schema name (``pkg/msg/Name``), times int ns."""

    name: str
    type: str
    schema_encoding: str
    message_encoding: str
    message_count: int
    first_ns: int | None
    last_ns: int | None
    rate_hz: float | None  # (count - 1) / (last - first); None with fewer than two messages


@dataclass(frozen=True)
class LogSummary:
    """What a log holds, read from its summary section (or a linear scan).

    ``topics`` are sorted by name and include topics without messages. ``compression``
    lists the chunk compressions found (``zstd``, ``lz4``, ``none``; ``unchunked`` for
    messages outside chunks). ``indexed`` is False when a file had to be scanned
    linearly; ``truncated_at`` names the first truncated file and byte offset (only
    possible when the log was opened with ``allow_truncated=True``).
    """

    path: Path
    files: tuple[Path, ...]
    profile: str
    library: str
    topics: tuple[TopicInfo, ...]
    message_count: int
    start_ns: int | None
    end_ns: int | None
    compression: tuple[str, ...]
    indexed: bool
    truncated_at: tuple[Path, int] | None = None
    bag_compression: str | None = None  # rosbag2's own: "zstd per message", "zstd per file" (bag_compression.py)

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        if self.start_ns is None or self.end_ns is None:
            return None
        return self.start_ns, self.end_ns

    def topic(self, name: str) -> TopicInfo:
        """The topic called ``name``; LogError naming the log and its topics if absent."""
        for t in self.topics:
            if t.name == name:
                return t
        raise LogError(f"{self.path}: topic {name!r} not found (topics: {_list(self.topic_names)})")

    def has_topic(self, name: str) -> bool:
        return any(t.name == name for t in self.topics)

    @property
    def topic_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.topics)


@dataclass(frozen=True)
class LogMessage:
    """One message: ``msg`` is the decoded ROS 2 message (attribute access), or the raw
    CDR bytes when read with ``decode=False``."""

    topic: str
    type: str
    log_time_ns: int
    publish_time_ns: int
    msg: Any


def _list(names: Iterable[str], limit: int = 12) -> str:
    names = list(names)
    if not names:
        return "none"
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


@dataclass
class _Block:
    """A chunk (or one message outside chunks) in the data section of one file."""

    start_ns: int
    end_ns: int
    offset: int  # of the record's opcode byte
    is_chunk: bool
    channels: frozenset[int] | None  # None: unknown (no message index), may hold any


class _ChannelStats:
    __slots__ = ("count", "first", "last")

    def __init__(self) -> None:
        self.count = 0
        self.first: int | None = None
        self.last: int | None = None

    def add(self, count: int, first: int, last: int) -> None:
        self.count += count
        self.first = first if self.first is None else min(self.first, first)
        self.last = last if self.last is None else max(self.last, last)


def _parse(record_type: Any, body: bytes | memoryview) -> Any:
    return record_type.read(ReadDataStream(io.BytesIO(bytes(body))))


def _iter_records(data: bytes | memoryview) -> Iterator[tuple[int, int, memoryview]]:
    """(opcode, offset, body) of each record in a chunk's uncompressed payload."""
    view = memoryview(data)
    pos, end = 0, len(view)
    while pos < end:
        if end - pos < 9:
            raise ValueError(f"record header at payload byte {pos} is cut off")
        op, length = _RECORD_HEAD.unpack_from(view, pos)
        if pos + 9 + length > end:
            raise ValueError(f"record at payload byte {pos} claims {length} bytes past the payload end")
        yield op, pos, view[pos + 9 : pos + 9 + length]
        pos += 9 + length


class _McapFile:
    """One .mcap file: header, schemas, channels, per-channel statistics and a block index."""

    def __init__(self, path: Path, allow_truncated: bool, source: Path | None = None):
        self.path = source or path  # named in errors: the bag's file, not a decompressed copy
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.stats: dict[int, _ChannelStats] = {}
        self.blocks: list[_Block] = []
        self.compressions: set[str] = set()
        self.indexed = False
        self.truncated_at: int | None = None
        try:
            self._fh = open(path, "rb")
        except OSError as err:
            raise LogError(f"{self.path}: cannot open ({err.strerror or err})") from err
        try:
            self.size = self._fh.seek(0, io.SEEK_END)
            self._open(allow_truncated)
        except BaseException:
            self._fh.close()
            raise

    def close(self) -> None:
        self._fh.close()

    # --- low-level reads ----------------------------------------------------------------

    def _read(self, offset: int, n: int) -> bytes:
        # Check before reading: a corrupt length or offset must not allocate n bytes first.
        if offset < 0 or n < 0 or offset + n > self.size:
            raise LogError(
                f"{self.path}: truncated or corrupt at byte {min(max(offset, 0), self.size)} (a record needs {n} bytes "
                f"at offset {offset} but the file has {self.size}; was the recording interrupted?)"
            )
        self._fh.seek(offset)
        data = self._fh.read(n)
        if len(data) != n:
            raise LogError(
                f"{self.path}: truncated at byte {self.size} (expected {n} bytes at offset {offset}; "
                "was the recording interrupted?)"
            )
        return data

    def _corrupt(self, what: str, offset: int, err: BaseException | str) -> LogError:
        detail = str(err) or type(err).__name__
        if "expected" not in detail:
            detail += f"; expected a well-formed MCAP {what}"
        return LogError(f"{self.path}: corrupt {what} at byte {offset} ({detail})")

    # --- opening --------------------------------------------------------------------------

    def _open(self, allow_truncated: bool) -> None:
        head = self._read(0, min(self.size, 8)) if self.size else b""
        if head != MAGIC:
            raise LogError(
                f"{self.path}: not an MCAP file (starts with {head[:8]!r}, expected the MCAP magic {MAGIC!r})"
            )
        op, length = _RECORD_HEAD.unpack(self._read_or_truncated(8, 9))
        if op != Opcode.HEADER:
            raise self._corrupt("header", 8, f"first record has opcode 0x{op:02x}, expected the Header record 0x01")
        try:
            header = _parse(Header, self._read_or_truncated(17, length))
        except LogError:
            raise
        except Exception as err:
            raise self._corrupt("header", 8, err) from err
        self.profile, self.library = header.profile, header.library
        self._data_start = 17 + length

        footer = self._footer()
        if footer is None:
            if not allow_truncated:
                raise LogError(
                    f"{self.path}: truncated MCAP file ({self.size} bytes; expected a Footer record and the "
                    "closing magic at the end; was the recording interrupted?)"
                )
            self._scan(allow_truncated=True)
            if self.truncated_at is None:  # the data section is whole; the summary is cut off
                self.truncated_at = self.size
            return
        if footer.summary_start == 0 or not self._load_summary(footer):
            self._scan(allow_truncated=False)

    def _read_or_truncated(self, offset: int, n: int) -> bytes:
        if offset + n > self.size:
            raise LogError(
                f"{self.path}: truncated at byte {self.size} (a record at offset {offset} needs {n} more bytes; "
                "was the recording interrupted?)"
            )
        return self._read(offset, n)

    def _footer(self) -> Footer | None:
        """The Footer record, or None when the file does not end with footer + magic."""
        if self.size < len(MAGIC) * 2 + _FOOTER_RECORD_SIZE:
            return None
        tail = self._read(self.size - len(MAGIC) - _FOOTER_RECORD_SIZE, _FOOTER_RECORD_SIZE + len(MAGIC))
        if tail[-8:] != MAGIC:
            return None
        op, length = _RECORD_HEAD.unpack_from(tail, 0)
        if op != Opcode.FOOTER or length != 20:
            return None
        footer = _parse(Footer, tail[9:29])
        if footer.summary_start > self.size - len(MAGIC) - _FOOTER_RECORD_SIZE:
            raise self._corrupt("footer", self.size - 37, f"summary start {footer.summary_start} is past the footer")
        return footer

    def _load_summary(self, footer: Footer) -> bool:
        """Read schemas, channels and chunk indexes from the summary section.

        Returns False when the summary has no chunk index but the file holds messages
        (then a linear scan is needed to find them).
        """
        footer_offset = self.size - len(MAGIC) - _FOOTER_RECORD_SIZE
        start = footer.summary_start
        data = self._read(start, footer_offset - start)
        chunk_indexes: list[ChunkIndex] = []
        statistics: Statistics | None = None
        try:
            for op, _pos, body in _iter_records(data):
                if op == Opcode.SCHEMA:
                    s = _parse(Schema, body)
                    self.schemas[s.id] = s
                elif op == Opcode.CHANNEL:
                    c = _parse(Channel, body)
                    self.channels[c.id] = c
                elif op == Opcode.CHUNK_INDEX:
                    chunk_indexes.append(_parse(ChunkIndex, body))
                elif op == Opcode.STATISTICS:
                    statistics = _parse(Statistics, body)
        except Exception as err:
            raise self._corrupt("summary section", start, err) from err
        if not chunk_indexes:
            if statistics is not None and statistics.message_count == 0:
                self.indexed = True
                self._ensure_stats()
                return True
            return False
        for ci in chunk_indexes:
            self.compressions.add(ci.compression or "none")
            channels = self._chunk_stats_from_index(ci)
            self.blocks.append(
                _Block(ci.message_start_time, ci.message_end_time, ci.chunk_start_offset, True, channels)
            )
        self.indexed = True
        self._ensure_stats()
        return True

    def _ensure_stats(self) -> None:
        for cid in self.channels:
            self.stats.setdefault(cid, _ChannelStats())

    def _chunk_stats_from_index(self, ci: ChunkIndex) -> frozenset[int]:
        """Per-channel counts and times of one chunk from its message index records
        (16 bytes per message); decompresses the chunk only if it has no message index."""
        if not ci.message_index_offsets or ci.message_index_length == 0:
            return self._chunk_stats_from_data(ci.chunk_start_offset)
        start = ci.chunk_start_offset + ci.chunk_length
        data = self._read(start, ci.message_index_length)
        try:
            for op, _pos, body in _iter_records(data):
                if op != Opcode.MESSAGE_INDEX:
                    continue
                cid, nbytes = struct.unpack_from("<HI", body, 0)
                if nbytes % 16 or 6 + nbytes > len(body):
                    raise ValueError(f"message index of channel {cid} has {nbytes} bytes of entries")
                if nbytes == 0:
                    continue
                times = np.frombuffer(body, dtype="<u8", count=nbytes // 8, offset=6)[0::2]
                self.stats.setdefault(cid, _ChannelStats()).add(len(times), int(times.min()), int(times.max()))
        except Exception as err:
            raise self._corrupt("message index", start, err) from err
        return frozenset(ci.message_index_offsets)

    def _chunk_stats_from_data(self, offset: int) -> frozenset[int]:
        channels: set[int] = set()
        for cid, log_time, _pub, _data in self._chunk_messages(offset, register=True):
            self.stats.setdefault(cid, _ChannelStats()).add(1, log_time, log_time)
            channels.add(cid)
        return frozenset(channels)

    def _scan(self, allow_truncated: bool) -> None:
        """Index the data section by reading it once from the start (no summary available)."""
        self.indexed = False
        pos = self._data_start
        while True:
            if pos >= self.size:
                self._truncated(pos, "the data section ends without a DataEnd record", allow_truncated)
                break
            if self.size - pos < 9:
                self._truncated(pos, "a record header is cut off", allow_truncated)
                break
            op, length = _RECORD_HEAD.unpack(self._read(pos, 9))
            if pos + 9 + length > self.size:
                self._truncated(pos, f"a record of {length} bytes is cut off", allow_truncated)
                break
            body_at = pos + 9
            try:
                if op == Opcode.SCHEMA:
                    s = _parse(Schema, self._read(body_at, length))
                    self.schemas[s.id] = s
                elif op == Opcode.CHANNEL:
                    c = _parse(Channel, self._read(body_at, length))
                    self.channels[c.id] = c
                elif op == Opcode.MESSAGE:
                    if length < _MESSAGE_HEAD.size:
                        raise ValueError(f"message record of {length} bytes (expected at least {_MESSAGE_HEAD.size})")
                    cid, _seq, log_time, _pub = _MESSAGE_HEAD.unpack(self._read(body_at, _MESSAGE_HEAD.size))
                    self.stats.setdefault(cid, _ChannelStats()).add(1, log_time, log_time)
                    self.blocks.append(_Block(log_time, log_time, pos, False, frozenset([cid])))
                    self.compressions.add("unchunked")
            except LogError:
                raise
            except Exception as err:
                raise self._corrupt(Opcode(op).name.lower() + " record", pos, err) from err
            if op == Opcode.CHUNK:
                start, end = struct.unpack("<QQ", self._read(body_at, 16))
                channels = self._chunk_stats_from_data(pos)
                self.blocks.append(_Block(start, end, pos, True, channels))
            elif op in (Opcode.DATA_END, Opcode.FOOTER):
                break
            pos = body_at + length
        self._ensure_stats()

    def _truncated(self, pos: int, what: str, allow_truncated: bool) -> None:
        if not allow_truncated:
            raise LogError(f"{self.path}: truncated at byte {pos} ({what}; expected a complete MCAP data section)")
        self.truncated_at = pos

    # --- chunks ---------------------------------------------------------------------------

    def _chunk_payload(self, offset: int) -> tuple[bytes, str]:
        """The uncompressed records of the Chunk record at ``offset``, CRC-checked."""
        op, length = _RECORD_HEAD.unpack(self._read(offset, 9))
        if op != Opcode.CHUNK:
            raise self._corrupt("chunk index", offset, f"points at a record with opcode 0x{op:02x}, not a Chunk")
        body = self._read(offset + 9, length)
        try:
            _start, _end, usize, crc, clen = struct.unpack_from("<QQQII", body, 0)
            compression = bytes(body[32 : 32 + clen]).decode()
            (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
            data = body[40 + clen : 40 + clen + dlen]
            if len(data) != dlen:
                raise ValueError(f"chunk data claims {dlen} bytes but the record holds {len(data)}")
        except Exception as err:
            raise self._corrupt("chunk", offset, err) from err
        expected = f"{compression or 'uncompressed'} data of {usize} bytes"
        try:
            if compression == "zstd":
                import zstandard

                payload = zstandard.ZstdDecompressor().decompress(data, max_output_size=usize)
            elif compression == "lz4":
                import lz4.frame

                payload = lz4.frame.decompress(data)
            elif compression == "":
                payload = data
            else:
                raise LogError(
                    f"{self.path}: chunk at byte {offset} uses compression {compression!r} "
                    "(expected zstd, lz4 or none)"
                )
        except LogError:
            raise
        except Exception as err:
            raise self._corrupt("chunk", offset, f"{type(err).__name__}: {err}; expected {expected}") from err
        if len(payload) != usize:
            raise self._corrupt("chunk", offset, f"decompressed to {len(payload)} bytes; expected {expected}")
        if crc != 0 and zlib.crc32(payload) != crc:
            raise self._corrupt(
                "chunk", offset,
                f"CRC 0x{zlib.crc32(payload):08x} does not match the stored 0x{crc:08x}; expected {expected}",
            )
        return payload, compression

    def _chunk_messages(self, offset: int, register: bool = False) -> Iterator[tuple[int, int, int, memoryview]]:
        """(channel_id, log_time, publish_time, data) of every message in the chunk at ``offset``."""
        payload, compression = self._chunk_payload(offset)
        if register:
            self.compressions.add(compression or "none")
        try:
            for op, _pos, body in _iter_records(payload):
                if op == Opcode.MESSAGE:
                    cid, _seq, log_time, pub = _MESSAGE_HEAD.unpack_from(body, 0)
                    yield cid, log_time, pub, body[_MESSAGE_HEAD.size :]
                elif register and op == Opcode.SCHEMA:
                    s = _parse(Schema, body)
                    self.schemas.setdefault(s.id, s)
                elif register and op == Opcode.CHANNEL:
                    c = _parse(Channel, body)
                    self.channels.setdefault(c.id, c)
        except (ValueError, struct.error, UnicodeDecodeError, McapError) as err:
            raise self._corrupt("chunk", offset, f"{type(err).__name__}: {err}") from err

    def _block_messages(self, block: _Block) -> Iterator[tuple[int, int, int, memoryview]]:
        if block.is_chunk:
            yield from self._chunk_messages(block.offset)
            return
        op, length = _RECORD_HEAD.unpack(self._read(block.offset, 9))
        body = memoryview(self._read(block.offset + 9, length))
        cid, _seq, log_time, pub = _MESSAGE_HEAD.unpack_from(body, 0)
        yield cid, log_time, pub, body[_MESSAGE_HEAD.size :]

    def iter_raw(
        self, channel_ids: set[int], start_ns: int | None, end_ns: int | None
    ) -> Iterator[tuple[int, int, int, int, memoryview]]:
        """(log_time, block#, position, channel_id, publish_time, data) in log-time order.

        Blocks are opened in order of their first message time and their messages merged
        through a heap, so memory holds only the blocks that overlap in time.
        """
        heap: list[tuple[Any, ...]] = []
        for i, b in enumerate(self.blocks):
            if start_ns is not None and b.end_ns < start_ns:
                continue
            if end_ns is not None and b.start_ns > end_ns:
                continue
            if b.channels is not None and not (b.channels & channel_ids):
                continue
            heapq.heappush(heap, (b.start_ns, 0, i, 0, None))
        while heap:
            log_time, kind, i, j, item = heapq.heappop(heap)
            if kind == 1:
                yield (log_time, i, j) + item
                continue
            for j, (cid, t, pub, data) in enumerate(self._block_messages(self.blocks[i])):
                if cid not in channel_ids:
                    continue
                if (start_ns is not None and t < start_ns) or (end_ns is not None and t > end_ns):
                    continue
                heapq.heappush(heap, (t, 1, i, j, (cid, pub, bytes(data))))


def _natural_key(path: Path) -> list[Any]:
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", path.name)]


def bag_files(path: str | Path) -> list[Path]:
    """The .mcap files of a log: ``[path]`` for a file; for a rosbag2 folder (or its
    metadata.yaml), the files listed in metadata.yaml, else every *.mcap in name order."""
    p = Path(path)
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if not p.exists():
        raise LogError(f"{p}: no such file or folder (expected an .mcap file or a rosbag2 bag folder)")
    if p.is_file():
        return [p]
    meta = p / "metadata.yaml"
    if meta.is_file():
        import yaml

        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        except Exception as err:
            raise LogError(
                f"{meta}: not a rosbag2 metadata file "
                f"({type(err).__name__}: {err}; expected rosbag2_bagfile_information)"
            ) from err
        storage = info.get("storage_identifier", "mcap")
        if storage != "mcap":
            raise LogError(f"{meta}: bag storage is {storage!r} (expected 'mcap')")
        names = info.get("relative_file_paths") or [f["path"] for f in info.get("files", [])]
        files = [p / n for n in names]
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise LogError(f"{meta}: lists files that are not in the folder: {_list(missing)}")
        if files:
            return files
    files = sorted(p.glob("*.mcap"), key=_natural_key)
    if not files:
        raise LogError(f"{p}: folder holds no .mcap files (expected a rosbag2 bag folder)")
    return files


def bag_compression(path: str | Path) -> str | None:
    """rosbag2's compression of a bag folder per its metadata.yaml (``"zstd per message"``,
    ``"zstd per file"``), or of a single whole-file compressed file by its suffix; None
    for plain bags and single .mcap files (their per-message compression, if any, is
    recognised message by message when reading)."""
    p = Path(path)
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if p.is_file():
        kind = file_compression(p)
        return f"{kind} per file" if kind else None
    meta = p / "metadata.yaml"
    if not meta.is_file():
        return None
    import yaml

    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
    except Exception:  # bag_files() has already named the problem
        return None
    mode = str(info.get("compression_mode", "") or "").upper()
    fmt = str(info.get("compression_format", "") or "zstd")
    return {"MESSAGE": f"{fmt} per message", "FILE": f"{fmt} per file"}.get(mode)


class McapLog:
    """A ROS 2 MCAP log: one .mcap file or a rosbag2 bag folder read as one log.

    ``allow_truncated`` reads a file that lacks its footer (an interrupted recording) up
    to its last complete record instead of raising. Use as a context manager, or call
    ``close()``.
    """

    def __init__(self, path: str | Path, *, allow_truncated: bool = False):
        self.path = Path(path)
        self._files: list[_McapFile] = []
        self._tmpdir: Path | None = None  # decompressed copies of whole-file compressed bag files
        try:
            for f in bag_files(self.path):
                if file_compression(f):
                    if self._tmpdir is None:
                        self._tmpdir = Path(tempfile.mkdtemp(prefix="mvtop-bag-"))
                    self._files.append(_McapFile(decompress_file(f, self._tmpdir), allow_truncated, source=f))
                else:
                    self._files.append(_McapFile(f, allow_truncated))
            self._bag_compression = bag_compression(self.path) or self._sniff_message_compression()
        except BaseException:
            self.close()
            raise
        self._decoders: dict[tuple[int, int], Callable[[bytes], Any]] = {}
        self._summary: LogSummary | None = None

    def _sniff_message_compression(self) -> str | None:
        """``"zstd per message"`` when the log's first message is a compressed frame (a
        message-compressed bag file without its metadata.yaml), else None."""
        f = self._files[0] if self._files else None
        if f is None or not f.blocks:
            return None
        try:
            first = next(f._block_messages(min(f.blocks, key=lambda b: b.start_ns)), None)
        except LogError:  # reported where the messages are read
            return None
        kind = message_compression(first[3]) if first is not None else None
        return f"{kind} per message" if kind else None

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        for f in self._files:
            f.close()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    @property
    def files(self) -> tuple[Path, ...]:
        return tuple(f.path for f in self._files)

    # --- summary ----------------------------------------------------------------------------

    def summary(self) -> LogSummary:
        """Topics, types, counts, rates and time range of the whole log."""
        if self._summary is not None:
            return self._summary
        merged: dict[str, dict[str, Any]] = {}
        for f in self._files:
            for cid, ch in f.channels.items():
                schema = f.schemas.get(ch.schema_id)
                type_name = schema.name if schema else ""
                entry = merged.setdefault(
                    ch.topic,
                    {
                        "type": type_name,
                        "schema_encoding": schema.encoding if schema else "",
                        "message_encoding": ch.message_encoding,
                        "stats": _ChannelStats(),
                    },
                )
                if normalize_type(entry["type"]) != normalize_type(type_name):
                    raise LogError(
                        f"{f.path}: topic {ch.topic!r} has type {type_name!r} here but {entry['type']!r} "
                        "elsewhere in the log (expected one type per topic)"
                    )
                st = f.stats.get(cid)
                if st is not None and st.count:
                    entry["stats"].add(st.count, st.first, st.last)
        topics = []
        for name in sorted(merged):
            e = merged[name]
            st = e["stats"]
            rate = None
            if st.count >= 2 and st.last > st.first:
                rate = (st.count - 1) / ((st.last - st.first) * 1e-9)
            topics.append(
                TopicInfo(
                    name, e["type"], e["schema_encoding"], e["message_encoding"], st.count, st.first, st.last, rate
                )
            )
        firsts = [t.first_ns for t in topics if t.first_ns is not None]
        lasts = [t.last_ns for t in topics if t.last_ns is not None]
        truncated = next(((f.path, f.truncated_at) for f in self._files if f.truncated_at is not None), None)
        self._summary = LogSummary(
            path=self.path,
            files=self.files,
            profile=self._files[0].profile,
            library=self._files[0].library,
            topics=tuple(topics),
            message_count=sum(t.message_count for t in topics),
            start_ns=min(firsts) if firsts else None,
            end_ns=max(lasts) if lasts else None,
            compression=tuple(sorted(set().union(*(f.compressions for f in self._files)))),
            indexed=all(f.indexed for f in self._files),
            truncated_at=truncated,
            bag_compression=self._bag_compression,
        )
        return self._summary

    def require_topics(self, topics: Mapping[str, str | None]) -> None:
        """Raise LogError for the first topic that is absent or has another type than
        expected (``None`` accepts any type). Types compare as ``pkg/msg/Name``."""
        summary = self.summary()
        for name, expected in topics.items():
            if not summary.has_topic(name):
                want = f"{expected} " if expected else ""
                raise LogError(
                    f"{self.path}: topic {name!r} not found "
                    f"(expected {want}messages; topics: {_list(summary.topic_names)})"
                )
            actual = summary.topic(name).type
            if expected and normalize_type(actual) != normalize_type(expected):
                raise LogError(f"{self.path}: topic {name!r} has type {actual!r} (expected {expected})")

    # --- messages ---------------------------------------------------------------------------

    def _decoder(self, fi: int, ch: Channel) -> Callable[[bytes], Any]:
        f = self._files[fi]
        key = (fi, ch.id)
        decoder = self._decoders.get(key)
        if decoder is not None:
            return decoder
        schema = f.schemas.get(ch.schema_id)
        if schema is None:
            raise LogError(f"{f.path}: topic {ch.topic!r} has no schema (expected a ros2msg schema)")
        if schema.encoding != "ros2msg" or ch.message_encoding != "cdr":
            raise LogError(
                f"{f.path}: topic {ch.topic!r} has schema encoding {schema.encoding!r} and message encoding "
                f"{ch.message_encoding!r} (expected 'ros2msg' schemas with 'cdr' messages, as rosbag2 writes)"
            )
        if normalize_type(schema.name) in MESSAGE_TYPES:
            # A type mvtop reads: its fields must be the ones the readers access (a schema
            # edited or corrupted in the file would otherwise decode into other attributes).
            try:
                problem = schema_mismatch(schema.name, bytes(schema.data).decode("utf-8"))
            except UnicodeDecodeError as err:
                problem = f"is not UTF-8 text ({err})"
            if problem is not None:
                raise LogError(
                    f"{f.path}: topic {ch.topic!r}: the {schema.name} schema stored in the log {problem} "
                    "(expected the ROS 2 message definition)"
                )
        from mcap_ros2.decoder import DecoderFactory

        try:
            # The vendored rosidl parser prints to stderr before raising; only the CLI prints.
            with contextlib.redirect_stderr(io.StringIO()):
                decoder = DecoderFactory().decoder_for(ch.message_encoding, schema)
        except Exception as err:
            raise LogError(
                f"{f.path}: cannot parse the ros2msg schema {schema.name!r} of topic {ch.topic!r} "
                f"({type(err).__name__}: {err})"
            ) from err
        if decoder is None:  # pragma: no cover - encodings checked above
            raise LogError(f"{f.path}: no decoder for topic {ch.topic!r}")
        self._decoders[key] = decoder
        return decoder

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        decode: bool = True,
    ) -> Iterator[LogMessage]:
        """Messages of ``topics`` (all when None) with ``start_ns <= log time <= end_ns``,
        in log-time order (ties in file order), across all files of the log.

        Raises LogError at once if a topic is absent or (with ``decode``) its schema is
        not a ros2msg schema; while iterating, if a chunk is corrupt or a message fails
        to decode (naming the topic and log time).
        """
        summary = self.summary()
        if isinstance(topics, str):
            topics = [topics]
        wanted = set(summary.topic_names) if topics is None else set(topics)
        for name in sorted(wanted):
            if not summary.has_topic(name):
                raise LogError(f"{self.path}: topic {name!r} not found (topics: {_list(summary.topic_names)})")
        streams: list[Iterator[tuple[tuple[int, int], LogMessage]]] = []
        for fi, f in enumerate(self._files):
            ids = {cid for cid, ch in f.channels.items() if ch.topic in wanted}
            if not ids:
                continue
            if decode:
                # Fail before the first message, not halfway through; channels without
                # messages are never decoded, so their schemas need not parse.
                for cid in ids:
                    if f.stats[cid].count:
                        self._decoder(fi, f.channels[cid])
            streams.append(self._file_messages(fi, ids, start_ns, end_ns, decode))
        merged = streams[0] if len(streams) == 1 else heapq.merge(*streams)  # merge() of none is empty
        return (m for _key, m in merged)

    def _file_messages(
        self, fi: int, ids: set[int], start_ns: int | None, end_ns: int | None, decode: bool
    ) -> Iterator[tuple[tuple[int, int], LogMessage]]:
        f = self._files[fi]
        for log_time, _b, _j, cid, pub, data in f.iter_raw(ids, start_ns, end_ns):
            ch = f.channels.get(cid)
            if ch is None:
                raise LogError(f"{f.path}: message at log time {log_time} ns refers to unknown channel {cid}")
            if log_time > MAX_TIME_NS:
                raise LogError(
                    f"{f.path}: message on topic {ch.topic!r} has log time {log_time} ns "
                    f"(expected at most {MAX_TIME_NS} ns, the largest int64 nanosecond time)"
                )
            schema = f.schemas.get(ch.schema_id)
            type_name = schema.name if schema else ""
            if data[:1] != b"\x00":  # not a CDR encapsulation header: rosbag2 per-message compression?
                data = decompress_message(data, f"{f.path}: message on topic {ch.topic!r} at log time {log_time} ns")
            msg: Any = data
            if decode:
                decoder = self._decoder(fi, ch)
                try:
                    msg = decoder(data)
                except Exception as err:
                    raise LogError(
                        f"{f.path}: message on topic {ch.topic!r} at log time {log_time} ns does not decode as "
                        f"{type_name} ({type(err).__name__}: {err})"
                    ) from err
            yield (log_time, fi), LogMessage(ch.topic, type_name, log_time, pub, msg)


def open_log(path: str | Path, *, allow_truncated: bool = False) -> McapLog:
    """Open a .mcap file or rosbag2 bag folder (see McapLog)."""
    return McapLog(path, allow_truncated=allow_truncated)


def read_summary(path: str | Path, *, allow_truncated: bool = False) -> LogSummary:
    """The LogSummary of a .mcap file or rosbag2 bag folder."""
    with McapLog(path, allow_truncated=allow_truncated) as log:
        return log.summary()
