"""Checkpoints of ``mvtop estimate``: stop a run anywhere, resume it at its last completed frame.

A run keeps its checkpoint in ``OUT/.mvtop-checkpoint/``:

* ``frames.bin``, a journal appended after every completed frame: one record per frame
  (the frame's estimate with its particles for track.mcap), so no per-frame result has to
  stay in memory and the outputs are written from it at the end;
* ``state.npz``, rewritten atomically after every frame: the particle set ``T_ee_object``
  (N, 4, 4) with its log-weights (N,), the random generator's state, the number of frames
  done, the journal's length at that frame, the run time so far [s] and the fingerprint of
  the run (log, resolved config, mesh files, mvtop version, and the options that change the
  outputs: ``--debug-images``).

Resuming restores the particles, the generator state and what the last frame's record
carries over (the sensor consistency watch), replays the log up to there (frame grouping and
the tactile reference images come out as before) and continues with the next frame, so a
resumed run writes the same track as an uninterrupted one with the same seed. A kill
between the two writes leaves a journal record past the recorded length; it is cut off on
resume. A checkpoint whose fingerprint differs from the run's is refused, naming the first
difference. The journal is read with an unpickler that accepts only numpy arrays and mvtop's
own dataclasses.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import os
import pickle
import shutil
import struct
import time
from array import array
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..config import Config, config_to_dict
from ..errors import EstimationError
from ..filter.particles import ParticleSet
from ..io.atomic import atomic_output
from ..io.mcap_reader import bag_files

CHECKPOINT_DIR = ".mvtop-checkpoint"
STATE_FILE = "state.npz"
JOURNAL_FILE = "frames.bin"
_FORMAT = 1
_LEN = struct.Struct("<Q")  # byte length of one journal record
_HASHED_BYTES = 1 << 20  # a log is identified by its size and its first and last MiB


class EstimateInterrupted(KeyboardInterrupt):
    """An estimate stopped by Ctrl-C (SIGINT) or SIGTERM: where it stopped, for the resume hint.

    ``frames_done`` frames are in the checkpoint at ``checkpoint_dir`` (0: nothing to resume);
    ``total`` is the number of frames the run would process; ``phase`` is ``"frames"`` or
    ``"outputs"`` (stopped while writing the final files); ``signum`` the signal's number.
    """

    def __init__(self, frames_done: int, total: int, checkpoint_dir: Path, phase: str, signum: int):
        super().__init__(f"interrupted after {frames_done} of {total} frames")
        self.frames_done = frames_done
        self.total = total
        self.checkpoint_dir = checkpoint_dir
        self.phase = phase
        self.signum = signum


class Terminated(KeyboardInterrupt):
    """Raised in the main thread by a SIGTERM handler, so that a terminated run cleans up like a
    Ctrl-C (temporary files removed, checkpoint kept) and reports where it stopped."""

    def __init__(self, signum: int):
        super().__init__(f"signal {signum}")
        self.signum = signum


# --- fingerprint -------------------------------------------------------------------------


def _file_digest(path: Path, whole: bool) -> str:
    """Size and SHA-256 of a file (``whole``) or of its size and first and last MiB."""
    h = hashlib.sha256()
    size = path.stat().st_size
    h.update(str(size).encode())
    with open(path, "rb") as fh:
        if whole or size <= 2 * _HASHED_BYTES:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        else:
            h.update(fh.read(_HASHED_BYTES))
            fh.seek(size - _HASHED_BYTES)
            h.update(fh.read(_HASHED_BYTES))
    return f"{size}:{h.hexdigest()[:32]}"


def fingerprint(log_path: Path, cfg: Config) -> dict[str, Any]:
    """What a checkpoint must match to be resumed: the log's files (name, size, and a hash of
    the size and first and last MiB), the resolved config (every key, with the command line's
    seed, particles and modalities applied), the content of the mesh and URDF files it names,
    and the mvtop version."""
    files = bag_files(log_path)
    named = [cfg.object.mesh, *(e.mesh for e in cfg.environment)]
    if cfg.robot.urdf is not None:
        named.append(cfg.robot.urdf)
    return {
        "mvtop": __version__,
        "log": [{"name": f.name, "bytes": f.stat().st_size, "digest": _file_digest(f, whole=False)} for f in files],
        "config": json.loads(json.dumps(config_to_dict(cfg), default=str)),
        "files": {Path(p).name: _file_digest(Path(p), whole=True) if Path(p).is_file() else "missing" for p in named},
    }


def _first_difference(saved: Any, current: Any, key: str) -> str | None:
    """The dotted key of the first difference between two JSON-like values, with both values."""
    if isinstance(saved, dict) and isinstance(current, dict):
        for k in list(saved) + [k for k in current if k not in saved]:
            sub = f"{key}.{k}" if key else str(k)
            if k not in saved or k not in current:
                return f"{sub} ({_short(saved.get(k))} in the checkpoint, {_short(current.get(k))} now)"
            diff = _first_difference(saved[k], current[k], sub)
            if diff is not None:
                return diff
        return None
    if isinstance(saved, list) and isinstance(current, list) and len(saved) == len(current):
        for i, (a, b) in enumerate(zip(saved, current)):
            diff = _first_difference(a, b, f"{key}[{i}]")
            if diff is not None:
                return diff
        return None
    if saved != current:
        return f"{key} ({_short(saved)} in the checkpoint, {_short(current)} now)"
    return None


def _short(v: Any) -> str:
    s = "absent" if v is None else json.dumps(v)
    return s if len(s) <= 80 else s[:77] + "..."


def _files(entries: Any) -> str:
    try:
        return ", ".join(f"{e['name']} of {e['bytes']} bytes" for e in entries)
    except (TypeError, KeyError):
        return "another log"


def describe_mismatch(saved: dict, current: dict) -> str | None:
    """One phrase naming what differs between two fingerprints (None when they match), e.g.
    ``config key filter.seed differs (0 in the checkpoint, 3 now)``."""
    for part, what in (("log", "log"), ("config", "config key "), ("files", "content of "), ("mvtop", "mvtop version"),
                       ("options", "option ")):
        diff = _first_difference(saved.get(part), current.get(part), "")
        if diff is None:
            continue
        if part == "log":
            return f"the log differs ({_files(saved.get('log'))} in the checkpoint, {_files(current['log'])} now)"
        if part == "mvtop":
            return f"the mvtop version differs ({saved.get('mvtop')} in the checkpoint, {current['mvtop']} now)"
        return f"{what}{diff.replace(' (', ' differs (', 1)}"
    return None


# --- the journal ---------------------------------------------------------------------------


class _SafeUnpickler(pickle.Unpickler):
    """Loads journal records: numpy arrays and scalars, and mvtop's dataclasses, nothing else."""

    _NUMPY = {"_frombuffer", "_reconstruct", "ndarray", "dtype", "scalar"}

    def find_class(self, module: str, name: str) -> Any:
        if (module == "numpy" or module.startswith("numpy.")) and name in self._NUMPY:
            return super().find_class(module, name)
        if module.startswith("mvtop_cli."):
            obj = super().find_class(module, name)
            if isinstance(obj, type) and dataclasses.is_dataclass(obj):
                return obj
        raise pickle.UnpicklingError(f"unexpected {module}.{name} in a checkpoint record")


class JournalResults(Sequence):
    """The per-frame estimates of a run, read back from its journal one at a time (a
    ``Sequence``: ``len``, indexing, iteration), so the results of a long log never all sit
    in memory."""

    def __init__(self, path: Path, offsets: array):
        self._path = path
        self._offsets = offsets  # byte offset of each record

    def __len__(self) -> int:
        return len(self._offsets)

    def _load(self, fh, offset: int) -> Any:
        fh.seek(offset)
        try:
            (n,) = _LEN.unpack(fh.read(_LEN.size))
            return _SafeUnpickler(io.BytesIO(fh.read(n))).load()
        except Exception as err:
            raise EstimationError(f"{self._path}: unreadable checkpoint record at byte {offset} "
                                  f"({type(err).__name__}: {err}); run without --resume to start over") from err

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(i)
        with open(self._path, "rb") as fh:
            return self._load(fh, self._offsets[i])

    def __iter__(self) -> Iterator[Any]:
        with open(self._path, "rb") as fh:
            for offset in self._offsets:
                yield self._load(fh, offset)


# --- the checkpoint ------------------------------------------------------------------------


@dataclasses.dataclass
class Restored:
    """What a resumed run starts from: the state after ``frames_done`` frames."""

    frames_done: int
    particles: ParticleSet | None
    rng_state: dict | None
    elapsed_s: float


class Checkpoint:
    """The checkpoint of one run in ``out_dir`` (see the module docstring).

    ``Checkpoint.start(out_dir, fp, resume=False)`` discards any checkpoint there and starts
    an empty one; with ``resume=True`` it loads the existing one (EstimationError when there is
    none, it is unreadable, or its fingerprint differs from ``fp``).
    """

    def __init__(self, out_dir: Path, fp: dict):
        self.dir = Path(out_dir) / CHECKPOINT_DIR
        self.fingerprint = fp
        self.frames_done = 0
        self.last_stamp_ns: int | None = None
        self._offsets = array("q")
        self._end = 0
        self._journal = None
        self.write_seconds = 0.0  # time spent writing the checkpoint in this session [s]
        self.writes = 0

    @property
    def state_path(self) -> Path:
        return self.dir / STATE_FILE

    @property
    def journal_path(self) -> Path:
        return self.dir / JOURNAL_FILE

    @classmethod
    def start(cls, out_dir: Path, fp: dict, resume: bool) -> tuple[Checkpoint, Restored]:
        ck = cls(out_dir, fp)
        _remove_stale_temporaries(Path(out_dir))
        if resume:
            restored = ck._load()
        else:
            if ck.dir.exists():
                shutil.rmtree(ck.dir)
            restored = Restored(0, None, None, 0.0)
        ck.dir.mkdir(parents=True, exist_ok=True)
        ck._journal = open(ck.journal_path, "r+b" if resume else "wb")
        ck._journal.truncate(ck._end)  # drop a record written after the last state (a kill between)
        ck._journal.seek(ck._end)
        return ck, restored

    def _load(self) -> Restored:
        where = self.dir
        if not self.state_path.is_file():
            raise EstimationError(
                f"{where}: no checkpoint to resume ({STATE_FILE} not found; a completed run removes it); "
                "run without --resume to start from the first frame"
            )
        try:
            with np.load(self.state_path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                poses = np.array(data["poses"]) if "poses" in data else None
                log_weights = np.array(data["log_weights"]) if "log_weights" in data else None
        except Exception as err:
            raise EstimationError(f"{self.state_path}: unreadable checkpoint ({type(err).__name__}: {err}); "
                                  "run without --resume to start over") from err
        if meta.get("format") != _FORMAT:
            raise EstimationError(f"{self.state_path}: checkpoint format {meta.get('format')!r} (expected {_FORMAT}); "
                                  "run without --resume to start over")
        mismatch = describe_mismatch(meta.get("fingerprint") or {}, self.fingerprint)
        if mismatch is not None:
            raise EstimationError(f"{where}: cannot resume: {mismatch}; run without --resume to start over")
        end = int(meta["journal_bytes"])
        offsets = self._scan_journal(end) if self.journal_path.is_file() else None
        if offsets is None or len(offsets) != meta["frames_done"]:
            raise EstimationError(f"{self.journal_path}: checkpoint journal does not match its state "
                                  f"({end} bytes and {meta['frames_done']} frames expected); "
                                  "run without --resume to start over")
        self.frames_done = int(meta["frames_done"])
        self.last_stamp_ns = meta.get("last_stamp_ns")
        self._offsets, self._end = offsets, end
        particles = None if poses is None else ParticleSet(poses, log_weights)
        return Restored(self.frames_done, particles, meta.get("rng_state"), float(meta.get("elapsed_s", 0.0)))

    def _scan_journal(self, end: int) -> array | None:
        """Offsets of the records in the journal's first ``end`` bytes (None if they do not
        end exactly there)."""
        offsets = array("q")
        pos = 0
        with open(self.journal_path, "rb") as fh:
            while pos < end:
                fh.seek(pos)
                head = fh.read(_LEN.size)
                if len(head) != _LEN.size:
                    return None
                offsets.append(pos)
                pos += _LEN.size + _LEN.unpack(head)[0]
        return offsets if pos == end else None

    def record(self, result: Any, particles: ParticleSet | None, rng: np.random.Generator, elapsed_s: float) -> None:
        """Checkpoint one completed frame: append ``result`` to the journal, then rewrite the
        state (particles, generator state, counts) atomically."""
        t0 = time.perf_counter()
        blob = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
        fh = self._journal
        assert fh is not None
        fh.write(_LEN.pack(len(blob)))
        fh.write(blob)
        fh.flush()
        os.fsync(fh.fileno())
        end = self._end + _LEN.size + len(blob)
        meta = {
            "format": _FORMAT,
            "fingerprint": self.fingerprint,
            "frames_done": self.frames_done + 1,
            "journal_bytes": end,
            "rng_state": rng.bit_generator.state,
            "elapsed_s": elapsed_s,
            "last_stamp_ns": int(getattr(result, "stamp_ns", 0)),
        }
        arrays: dict[str, np.ndarray] = {"meta": np.array(json.dumps(meta))}
        if particles is not None:
            arrays["poses"] = np.asarray(particles.poses)
            arrays["log_weights"] = np.asarray(particles.log_weights)
        with atomic_output(self.state_path) as out:
            np.savez(out, **arrays)
        self._offsets.append(self._end)
        self._end = end
        self.frames_done += 1
        self.last_stamp_ns = meta["last_stamp_ns"]
        self.write_seconds += time.perf_counter() - t0
        self.writes += 1

    def saved_frames(self) -> int:
        """Frames the state on disk records, what ``--resume`` continues after: one more than
        ``frames_done`` when a signal lands between ``record``'s atomic write of the state and
        its count in memory."""
        return progress(self.dir.parent)[0]

    def results(self, limit: int | None = None) -> JournalResults:
        """The journaled per-frame results (the first ``limit`` of them)."""
        if self._journal is not None:
            self._journal.flush()
        offsets = array("q", self._offsets if limit is None else self._offsets[:limit])
        return JournalResults(self.journal_path, offsets)

    def close(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def remove(self) -> None:
        """Delete the checkpoint (after the outputs are written)."""
        self.close()
        shutil.rmtree(self.dir, ignore_errors=True)


def progress(out_dir: Path) -> tuple[int, float]:
    """(frames done, run time so far [s]) recorded in the checkpoint in ``out_dir``; (0, 0.0)
    when there is none or it is unreadable."""
    path = Path(out_dir) / CHECKPOINT_DIR / STATE_FILE
    with contextlib.suppress(Exception):
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            return int(meta["frames_done"]), float(meta["elapsed_s"])
    return 0, 0.0


def frames_done(out_dir: Path) -> int:
    """Frames recorded in the checkpoint in ``out_dir`` (0 when there is none or it is unreadable)."""
    return progress(out_dir)[0]


_OUTPUTS = ("track.mcap", "track.csv", "summary.json", "config.resolved.yaml", STATE_FILE)


def _remove_stale_temporaries(out_dir: Path) -> None:
    """Delete temporary files of the outputs left by a killed run (``.NAME.PID.HEX.tmp``, see
    io.atomic) whose process no longer exists."""
    for folder in (out_dir, out_dir / CHECKPOINT_DIR):
        if not folder.is_dir():
            continue
        for p in folder.glob(".*.tmp"):
            parts = p.name[1:].rsplit(".", 3)
            if len(parts) != 4 or parts[0] not in _OUTPUTS or not parts[1].isdigit():
                continue
            if int(parts[1]) != os.getpid() and not _alive(int(parts[1])):
                with contextlib.suppress(OSError):
                    p.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
