"""rosbag2's own compression, on top of MCAP's chunk compression.

``ros2 bag record --compression-mode message --compression-format zstd`` compresses the
CDR bytes of every message separately (metadata.yaml: ``compression_mode: MESSAGE``):
the MCAP file is plain, each message's data is a zstd frame. ``--compression-mode file``
compresses each finished .mcap file whole into ``NAME.mcap.zstd``.

Message data is recognised by its first bytes: a CDR message starts with its 4-byte
encapsulation header, whose first byte is 0, while a zstd frame starts with the magic
``28 b5 2f fd`` and an lz4 frame with ``04 22 4d 18``. The check needs no metadata, so a
message-compressed .mcap file copied out of its bag folder reads as well.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ..errors import LogError

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
LZ4_FRAME_MAGIC = b"\x04\x22\x4d\x18"
FILE_SUFFIXES = {".zstd": "zstd", ".zst": "zstd", ".lz4": "lz4"}


def message_compression(data: bytes | memoryview) -> str | None:
    """``"zstd"`` or ``"lz4"`` when ``data`` is a compressed frame, None for plain CDR."""
    head = bytes(data[:4])
    if head == ZSTD_MAGIC:
        return "zstd"
    if head == LZ4_FRAME_MAGIC:
        return "lz4"
    return None


def decompress_message(data: bytes, where: str) -> bytes:
    """The CDR bytes of one message, decompressed if rosbag2 compressed it (see module doc).

    ``where`` names the file, topic and log time for the one-line LogError on a corrupt frame.
    """
    kind = message_compression(data)
    if kind is None:
        return data
    try:
        if kind == "zstd":
            import zstandard

            # decompressobj: rosbag2's frames carry their content size, but the format does not require it.
            obj = zstandard.ZstdDecompressor().decompressobj()
            out = obj.decompress(data)
            if not obj.eof:
                raise ValueError(f"the frame ends early ({len(data)} bytes hold no complete frame)")
            return out
        import lz4.frame

        return lz4.frame.decompress(data)
    except Exception as err:
        raise LogError(
            f"{where}: message data starts like a {kind} frame but does not decompress "
            f"({type(err).__name__}: {err}; expected rosbag2 per-message {kind} compression of CDR data)"
        ) from None


def file_compression(path: Path) -> str | None:
    """``"zstd"`` / ``"lz4"`` for a whole-file compressed bag file (by suffix), else None."""
    return FILE_SUFFIXES.get(Path(path).suffix.lower())


def decompress_file(src: Path, dst_dir: Path) -> Path:
    """Stream-decompress the whole-file compressed ``src`` (``NAME.mcap.zstd``) into
    ``dst_dir/NAME.mcap`` and return that path; memory use stays at the codec's buffers."""
    kind = file_compression(src)
    dst = Path(dst_dir) / Path(src).stem
    if dst.suffix != ".mcap":
        dst = dst.with_name(dst.name + ".mcap")
    try:
        with open(src, "rb") as fin, open(dst, "wb") as fout:
            if kind == "zstd":
                import zstandard

                with zstandard.ZstdDecompressor().stream_reader(fin, read_across_frames=True) as reader:
                    shutil.copyfileobj(reader, fout, 1 << 20)
            elif kind == "lz4":
                import lz4.frame

                with lz4.frame.open(fin, "rb") as reader:
                    shutil.copyfileobj(reader, fout, 1 << 20)
            else:
                raise LogError(f"{src}: unknown whole-file compression (expected a .zstd or .lz4 file)")
    except LogError:
        raise
    except OSError as err:
        if isinstance(err, FileNotFoundError) and not Path(src).exists():
            raise LogError(f"{src}: no such file (listed in the bag's metadata.yaml)") from None
        raise LogError(f"{src}: cannot decompress the {kind} bag file into {dst_dir} ({err})") from None
    except Exception as err:
        raise LogError(
            f"{src}: does not decompress as {kind} ({type(err).__name__}: {err}; expected a rosbag2 "
            f"file-compressed .mcap.{kind})"
        ) from None
    return dst
