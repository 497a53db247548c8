"""The job list of a batch estimate: one ``EstimateJob`` per log.

Logs come from LOG arguments (an .mcap file, a rosbag2 folder, a folder of logs, or a glob
pattern such as ``'logs/**/*.mcap'``) or from a manifest, a CSV or YAML table with one row per
log: ``log`` (required), ``config``, ``seed``, ``modalities``, ``particles``, ``max_frames`` and
``name`` (all optional; the command line's options are the defaults). Relative paths in a
manifest are relative to the manifest's folder. Every path is made absolute, so a job means
the same on any worker that mounts the same files at the same place.

Each job writes into ``OUT/NAME``: NAME is the log's file name without ``.mcap`` (its path
relative to a folder argument, for logs found in a folder), or the manifest's ``name``.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import os
import shlex
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import yaml

from .. import __version__
from ..config import MODALITIES
from ..errors import MvtopError

MANIFEST_COLUMNS = ("log", "config", "seed", "modalities", "particles", "max_frames", "name")
_GLOB_CHARS = "*?["


@dataclass(frozen=True)
class EstimateJob:
    """One log to estimate: inputs and options (absolute paths) and its output folder."""

    name: str
    log: str
    config: str
    out: str
    modalities: tuple[str, ...] | None = None
    particles: int | None = None
    seed: int | None = None
    max_frames: int | None = None

    def command(self) -> list[str]:
        """The single-log ``mvtop estimate`` command that makes the same outputs."""
        args = ["mvtop", "estimate", self.log, "--config", self.config, "--out", self.out]
        for flag, value in (("--modalities", None if self.modalities is None else ",".join(self.modalities)),
                            ("--particles", self.particles), ("--seed", self.seed), ("--max-frames", self.max_frames)):
            if value is not None:
                args += [flag, str(value)]
        return args

    def command_line(self) -> str:
        return shlex.join(self.command())

    def key(self) -> str:
        """What a finished run must match to be skipped on a re-run (SHA-256, 16 hex digits):
        the job's options, the log's size and modification time, the config file's bytes and
        the mvtop version."""
        def stat(path: str) -> list[int] | None:
            try:
                st = Path(path).stat()
            except OSError:
                return None
            return [st.st_size, st.st_mtime_ns] if Path(path).is_file() else [_folder_stat(Path(path))]

        data = {**asdict(self), "log_stat": stat(self.log), "config_sha256": _file_sha256(self.config),
                "mvtop": __version__}
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def _folder_stat(folder: Path) -> int:
    """A number that changes when a rosbag2 folder's files change (sizes and times)."""
    h = hashlib.sha256()
    for p in sorted(folder.iterdir()):
        if p.is_file():
            st = p.stat()
            h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return int(h.hexdigest()[:12], 16)


_SHA_CACHE: dict[tuple[str, int, int], str | None] = {}


def _file_sha256(path: str) -> str | None:
    try:
        st = Path(path).stat()
    except OSError:
        return None
    key = (path, st.st_size, st.st_mtime_ns)
    if key not in _SHA_CACHE:
        _SHA_CACHE[key] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return _SHA_CACHE[key]


def is_bag_folder(path: Path) -> bool:
    """A rosbag2 folder: one log, not a folder of logs."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def is_batch_input(arg: str | Path) -> bool:
    """Whether a single LOG argument asks for a batch: a folder that is not a rosbag2 folder,
    or a glob pattern that is not itself an existing path."""
    p = Path(arg)
    if p.exists():
        return p.is_dir() and not is_bag_folder(p)
    return any(c in str(arg) for c in _GLOB_CHARS)


def logs_in_folder(folder: Path) -> list[tuple[str, Path]]:
    """(name, path) of the logs under ``folder``: every .mcap file and rosbag2 folder (whose
    files are one log), searched recursively, in path order; the name is the path relative to
    ``folder`` without ``.mcap``."""
    found: list[tuple[str, Path]] = []

    def walk(d: Path) -> None:
        for p in sorted(d.iterdir()):
            if is_bag_folder(p):
                found.append((p.relative_to(folder).as_posix(), p))
            elif p.is_dir():
                walk(p)
            elif p.suffix == ".mcap":
                found.append((p.relative_to(folder).with_suffix("").as_posix(), p))

    walk(folder)
    return found


def _log_name(path: Path) -> str:
    return path.stem if path.suffix == ".mcap" else path.name


def jobs_from_arguments(args: list[str], config: Path | None, out: Path, defaults: dict[str, Any]) -> list[EstimateJob]:
    """One job per log named by ``args`` (files, rosbag2 folders, folders of logs, glob
    patterns), all with ``config`` and the command line's options ``defaults``."""
    if config is None:
        raise MvtopError("estimate needs --config CFG (see configs/), or a --manifest with a config column")
    named: list[tuple[str, Path]] = []
    for arg in args:
        p = Path(arg)
        if p.is_dir() and not is_bag_folder(p):
            logs = logs_in_folder(p)
            if not logs:
                raise MvtopError(f"{arg}: no log in this folder (expected .mcap files or rosbag2 folders)")
            named += logs
        elif not p.exists() and any(c in arg for c in _GLOB_CHARS):
            matches = sorted(glob.glob(arg, recursive=True))
            matches = [m for m in matches if Path(m).is_file() or is_bag_folder(Path(m))]
            if not matches:
                raise MvtopError(f"{arg}: the pattern matches no log (expected .mcap files or rosbag2 folders)")
            named += [(_log_name(Path(m)), Path(m)) for m in matches]
        else:  # a log; a missing one fails as its own job, in the results table
            named.append((_log_name(p), p))
    return _jobs(named, [(config, defaults)] * len(named), out, "LOG arguments")


def jobs_from_manifest(manifest: Path, config: Path | None, out: Path, defaults: dict[str, Any]) -> list[EstimateJob]:
    """One job per row of a CSV (header row) or YAML (a list of mappings) manifest."""
    rows = _read_manifest(manifest)
    named, settings = [], []
    base = manifest.resolve().parent
    for n, row in enumerate(rows, 1):
        where = f"{manifest} row {n}"
        unknown = [k for k in row if k not in MANIFEST_COLUMNS]
        if unknown:
            raise MvtopError(f"{where}: unknown column {unknown[0]!r} (expected {', '.join(MANIFEST_COLUMNS)})")
        if not row.get("log"):
            raise MvtopError(f"{where}: no log (expected a log path in the 'log' column)")
        log = Path(os.path.normpath(base / str(row["log"])))
        cfg = Path(os.path.normpath(base / str(row["config"]))) if row.get("config") not in (None, "") else config
        if cfg is None:
            raise MvtopError(f"{where}: no config (expected a 'config' column or --config CFG)")
        opts = dict(defaults)
        for key in ("seed", "particles", "max_frames"):
            if row.get(key) not in (None, ""):
                opts[key] = _integer(row[key], f"{where}: {key}", 0 if key == "seed" else 1)
        if row.get("modalities") not in (None, ""):
            opts["modalities"] = parse_modalities(row["modalities"], f"{where}: modalities")
        name = str(row["name"]) if row.get("name") not in (None, "") else _log_name(log)
        named.append((name, log))
        settings.append((cfg, opts))
    if not named:
        raise MvtopError(f"{manifest}: the manifest lists no log")
    return _jobs(named, settings, out, str(manifest))


def _read_manifest(path: Path) -> list[dict]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MvtopError(f"{path}: manifest not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise MvtopError(f"{path}: unreadable manifest ({err})") from None
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        if reader.fieldnames is None or "log" not in [f.strip() for f in reader.fieldnames]:
            raise MvtopError(f"{path}: expected a CSV header row with a 'log' column")
        return [{(k or "").strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items()} for r in reader]
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            raise MvtopError(f"{path}: not YAML ({str(err).splitlines()[0]})") from None
        if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
            raise MvtopError(f"{path}: expected a YAML list of mappings with a 'log' key each")
        return data
    raise MvtopError(f"{path}: expected a manifest ending in .csv, .yaml or .yml")


def _integer(value: Any, where: str, lo: int) -> int:
    try:
        v = int(str(value))
    except ValueError:
        raise MvtopError(f"{where}: expected an integer, got {value!r}") from None
    if v < lo:
        raise MvtopError(f"{where}: expected an integer >= {lo}, got {v}")
    return v


def parse_modalities(value: Any, where: str) -> tuple[str, ...]:
    """A comma-separated string (or a YAML list) of modalities, checked."""
    items = value if isinstance(value, list) else str(value).split(",")
    mods = tuple(str(m).strip() for m in items if str(m).strip())
    bad = [m for m in mods if m not in MODALITIES]
    if bad or not mods:
        raise MvtopError(f"{where}: expected a comma-separated subset of {','.join(MODALITIES)}, got {value!r}")
    return mods


def _jobs(named: list[tuple[str, Path]], settings: list[tuple[Path, dict]], out: Path,
          source: str) -> list[EstimateJob]:
    """The jobs of (name, log) with (config, options) each; one output folder per name."""
    seen: dict[str, Path] = {}
    jobs = []
    for (name, log), (cfg, opts) in zip(named, settings, strict=True):
        if name in seen:
            raise MvtopError(f"{source}: two logs would write to {out / name} ({seen[name]} and {log}); give them "
                             "different file names, or list them in a manifest with a 'name' column")
        if name.startswith(".") or ".." in Path(name).parts or Path(name).is_absolute():
            raise MvtopError(f"{source}: {name!r} is not usable as an output folder name")
        seen[name] = log
        jobs.append(EstimateJob(
            name=name, log=str(log.absolute()), config=str(Path(cfg).absolute()), out=str((out / name).absolute()),
            modalities=opts.get("modalities"), particles=opts.get("particles"), seed=opts.get("seed"),
            max_frames=opts.get("max_frames"),
        ))
    return jobs
