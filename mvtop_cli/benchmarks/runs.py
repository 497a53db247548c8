"""What the simulated benchmarks (``accuracy``, ``insertion``) share: a folder of runs, one
``runs/<name>/result.json`` per finished run, so that an interrupted benchmark resumes where it
stopped; the runs made on the batch engine (``batch/engine.py``: local processes or Ray tasks)
with progress; each invocation's wall time in ``invocations.jsonl``; the fingerprint of the
code that made a run; one simulated camera scene, one kind of camera masks (made from the images,
or a simulated segmenter's recorded with them: ``--recorded-masks-px``) and one set of config
settings (``--set``) per folder (``check_scene``, ``check_masks``, ``check_settings``); and the
compact, byte-reproducible ``results.jsonl.gz``.
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import json
import os
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Hashable, Mapping

from ..errors import MvtopError
from ..io.atomic import atomic_output

INVOCATIONS_FILE = "invocations.jsonl"
RESULT_FILE = "result.json"


@functools.lru_cache(maxsize=4)
def code_fingerprint(package: Path | None = None) -> str:
    """SHA-256 (first 12 hex digits) over the package's Python sources, relative path and
    bytes, in path order: runs made by the same code carry the same fingerprint."""
    root = Path(package) if package is not None else Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def finished_runs(jobs: list[tuple[Hashable, Path]]) -> tuple[dict, list[tuple[Hashable, Path]]]:
    """The reports of the jobs (key, run folder) whose ``result.json`` exists, and the jobs
    still to run."""
    reports, todo = {}, []
    for key, run_dir in jobs:
        result = Path(run_dir) / RESULT_FILE
        if result.is_file():
            reports[key] = json.loads(result.read_text())
        else:
            todo.append((key, run_dir))
    return reports, todo


def plan_runs(out_dir: Path, objects, methods, poses: int, first_seed: int, scene: str,
              import_results: Path | None, read_results: Callable[[Path], list[dict]], summary_only: bool,
              settings: Mapping[str, Any] | None = None, recorded_masks_px: int | None = None
              ) -> tuple[list[tuple[Hashable, Path]], dict, list[tuple[Hashable, Path]], int]:
    """A benchmark's runs in ``out_dir/runs``: every (object, seed, method) job in grasp-major
    order (a partial benchmark holds the same grasps of every object and method, so its tables
    compare like with like), the records of ``import_results`` (read by ``read_results``)
    written as their results, the finished reports checked for one camera ``scene``, one kind
    of camera masks (``recorded_masks_px``) and one set of config ``settings``, and the jobs
    still to run (none with ``summary_only``, which needs a finished run). Returns ``(jobs,
    reports, todo, imported)``."""
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    jobs = [((obj, first_seed + i, method), out_dir / "runs" / f"{obj}_{first_seed + i}_{method}")
            for i in range(poses) for obj in objects for method in methods]
    imported = 0
    if import_results is not None:
        imported = import_records(Path(import_results), read_results(Path(import_results)), jobs)
    reports, todo = finished_runs(jobs)
    check_scene(out_dir, reports, scene)
    check_masks(out_dir, reports, recorded_masks_px)
    check_settings(out_dir, reports, settings or {})
    if summary_only:
        todo = []
        if not reports:
            raise MvtopError(f"{out_dir}: no finished run of the requested objects, grasps and methods to summarise "
                             "(expected runs/*/result.json, or --import-results FILE)")
    return jobs, reports, todo, imported


def scene_record(scene: str) -> dict:
    """What a run's ``benchmark`` record notes of its simulated camera scene
    (``pipelines.simulate.SCENES``): nothing for the default scene, so records made before
    scenes existed read as default-scene runs."""
    return {"scene": scene} if scene != "default" else {}


def check_scene(out_dir: Path, reports: dict, scene: str) -> None:
    """A benchmark folder holds the runs of one camera scene: a finished (or imported) run of
    another scene than ``scene`` is an error naming the folder."""
    for report in reports.values():
        made_in = report.get("benchmark", {}).get("scene", "default")
        if made_in != scene:
            raise MvtopError(f"{out_dir}: holds runs of the {made_in!r} scene, not {scene!r} "
                             "(expected one scene per benchmark folder: give another --out)")


def simulated_sensors(scene: str, recorded_masks_px: int | None, frames: int | None = None):
    """The simulator's ``SimulateOptions`` for a benchmark's runs: its camera ``scene``; with
    ``recorded_masks_px`` N, each camera image's object mask recorded with it, as a segmenter
    node on the robot would publish it (outlines off by up to N px; the scene config then reads
    it with the ``topic`` backend), else none; ``frames`` per episode (None: the simulator's)."""
    from dataclasses import replace

    from ..pipelines.simulate import SimulateOptions, scene_options
    from ..sim.episode import EpisodeOptions

    options = SimulateOptions() if frames is None else SimulateOptions(episode=EpisodeOptions(frames=frames))
    options = scene_options(options, scene)
    if recorded_masks_px is not None:
        options = replace(options, mask_topics=True, mask_error_px=recorded_masks_px)
    return options


def masks_record(recorded_masks_px: int | None) -> dict:
    """What a run's ``benchmark`` record notes of its camera masks: nothing for masks made from
    the images, so records made before recorded masks existed read as such."""
    return {} if recorded_masks_px is None else {"recorded_masks_px": recorded_masks_px}


def masks_text(recorded_masks_px: int | None) -> str:
    """The camera masks of ``recorded_masks_px`` as a command line would ask for them."""
    return "camera masks made from the images" if recorded_masks_px is None else \
        f"--recorded-masks-px {recorded_masks_px}"


def masks_note(recorded_masks_px: int | None) -> str:
    """What a table's header adds for recorded camera masks, or nothing."""
    if recorded_masks_px is None:
        return ""
    outline = "exact" if recorded_masks_px == 0 else f"outlines off by up to {recorded_masks_px} px"
    return f", camera masks recorded by a simulated segmenter ({outline})"


def check_masks(out_dir: Path, reports: dict, recorded_masks_px: int | None) -> None:
    """A benchmark folder holds the runs of one kind of camera masks: a finished (or imported)
    run made with others is an error naming the folder and both."""
    for report in reports.values():
        made = report.get("benchmark", {}).get("recorded_masks_px")
        if made != recorded_masks_px:
            raise MvtopError(f"{out_dir}: its runs were made with {masks_text(made)}, not "
                             f"{masks_text(recorded_masks_px)} (one setting per benchmark folder: give another --out)")


def settings_record(settings: Mapping[str, Any] | None) -> dict:
    """What a run's ``benchmark`` record notes of the config settings it ran with (``--set``,
    ``config.parse_settings``): nothing without any, so records made before settings existed
    read as runs without."""
    return {"settings": dict(settings)} if settings else {}


def settings_text(settings: Mapping[str, Any] | None) -> str:
    """``--set KEY=VALUE ...`` as a command line would give ``settings``, or ``no --set``."""
    if not settings:
        return "no --set"
    return " ".join(f"--set {k}={v if isinstance(v, str) else json.dumps(v)}" for k, v in settings.items())


def settings_note(settings: Mapping[str, Any] | None) -> str:
    """What a table's header adds for a folder's settings: ``", --set KEY=VALUE ..."``, or nothing."""
    return f", {settings_text(settings)}" if settings else ""


def check_settings(out_dir: Path, reports: dict, settings: Mapping[str, Any]) -> None:
    """A benchmark folder holds the runs of one set of config settings: a finished (or
    imported) run made with other ``--set`` values than ``settings`` is an error naming the
    folder and both."""
    for report in reports.values():
        made = report.get("benchmark", {}).get("settings", {})
        if made != dict(settings):
            raise MvtopError(f"{out_dir}: its runs were made with {settings_text(made)}, not {settings_text(settings)} "
                             "(one setting per benchmark folder: give another --out)")


def check_settings_apply(sources, settings: Mapping[str, Any] | None, sensors=None) -> None:
    """Each object's scene config, as a benchmark writes it (``sources``: object names or
    object files; ``sensors``: ``pipelines.simulate.SimulateOptions``), must load with
    ``settings`` over it: an unknown key or a bad value stops the benchmark before any run,
    with the config loader's message on ``--set``."""
    if not settings:
        return
    from ..config import load_config
    from ..errors import ConfigError
    from ..pipelines.simulate import write_scene_config

    with tempfile.TemporaryDirectory(prefix="mvtop-settings-") as tmp:
        for source in sources:
            path = Path(tmp) / "config.yaml"
            write_scene_config(source, path, sensors)
            try:
                load_config(path, settings)
            except ConfigError as err:
                message = str(err).removeprefix(f"{path}: ")  # (apply_settings' own errors name --set)
                raise ConfigError(message if message.startswith("--set") else f"--set: {message}") from None


def run_jobs(fn: Callable, todo: list[tuple[Hashable, Path]], args_of: Callable[[Hashable, Path, int], tuple],
             reports: dict, total: int, engine, progress: Callable[[int, int], None] | None = None) -> float:
    """Run ``fn(*args_of(key, run_dir, threads))`` for every job in ``todo`` on ``engine``
    (``batch.engine.make_engine``: local processes or Ray tasks; the caller makes it before
    any output, so that an unreachable cluster stops the benchmark before its folder exists)
    and put each returned report into ``reports`` under its key; ``fn`` writes the run's
    ``result.json`` itself. A run's error stops the benchmark (the finished runs stay).
    ``progress(done, total)`` after each run and once at the start. Returns the wall time [s]."""
    done = len(reports)
    if progress is not None:
        progress(done, total)
    t0 = time.perf_counter()
    args = [args_of(key, run_dir, engine.threads) for key, run_dir in todo]
    for outcome in engine.run(fn, args):
        if outcome.error is not None:
            raise outcome.error
        reports[todo[outcome.index][0]] = outcome.value
        done += 1
        if progress is not None:
            progress(done, total)
    return time.perf_counter() - t0


def write_result(run_dir: Path, report: dict) -> None:
    """A run's ``result.json`` (atomically: a run counts as finished only once it is whole)."""
    Path(run_dir).mkdir(parents=True, exist_ok=True)
    with atomic_output(Path(run_dir) / RESULT_FILE, "w") as fh:
        json.dump(report, fh)


def append_invocation(out_dir: Path, workers: int, ran: int, imported: int, seconds: float) -> None:
    """One line in ``invocations.jsonl``: when this invocation finished, its wall time and runs."""
    entry = {"finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "seconds": round(seconds, 1),
             "runs_made": ran, "runs_imported": imported, "workers": workers,
             "cpus": os.cpu_count(), "code": code_fingerprint()}
    with (Path(out_dir) / INVOCATIONS_FILE).open("a") as fh:
        fh.write(json.dumps(entry) + "\n")


def totals(out_dir: Path, reports: dict) -> dict:
    """Time spent over the whole benchmark (all invocations of this folder) and which code
    made its runs (from each report's ``benchmark`` record)."""
    invocations = []
    path = Path(out_dir) / INVOCATIONS_FILE
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                invocations.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut by a crash: its time is not counted
    bench = [r.get("benchmark", {}) for r in reports.values()]
    codes = Counter(b.get("code", "unrecorded") for b in bench)
    return {
        "invocations": len(invocations),
        "wall_seconds_all_invocations": round(sum(float(i.get("seconds", 0.0)) for i in invocations), 1),
        "run_seconds_sum": round(sum(float(b.get("seconds", 0.0)) for b in bench), 1),
        "run_cpu_seconds_sum": round(sum(float(b.get("cpu_seconds", 0.0)) for b in bench), 1),
        "simulate_seconds_sum": round(sum(float(b.get("simulate_seconds", 0.0)) for b in bench), 1),
        "runs_without_simulate_time": sum("simulate_seconds" not in b for b in bench),
        "code_versions": dict(sorted(codes.items())),
    }


def write_jsonl_gz(path: Path, records: list[dict]) -> None:
    """One JSON line per record (sorted keys), gzip'ed without a time stamp in the header:
    byte-identical for the same records."""
    lines = [json.dumps(r, sort_keys=True) for r in records]
    data = ("\n".join(lines) + "\n").encode() if lines else b""
    with atomic_output(path, "wb") as fh:
        with gzip.GzipFile(fileobj=fh, mode="wb", mtime=0, filename="") as gz:
            gz.write(data)


def read_jsonl(path: Path, expected: str) -> list[tuple[int, object]]:
    """(line number, JSON value) of every non-empty line of a gzip'ed or plain JSON-lines file;
    a missing or damaged file, or a line that is not JSON, is an error naming the file (and
    line). ``expected``: the file name to suggest when it is missing."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        text = (gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw).decode("utf-8")
    except FileNotFoundError:
        raise MvtopError(f"{path}: results file not found (expected an {expected} of a benchmark folder)") from None
    except (OSError, EOFError, UnicodeDecodeError) as e:
        raise MvtopError(f"{path}: not a readable results file ({e})") from None
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append((n, json.loads(line)))
        except json.JSONDecodeError as e:
            raise MvtopError(f"{path} line {n}: not JSON ({e.msg})") from None
    return out


def import_records(path: Path, records: list[dict], jobs: list[tuple[Hashable, Path]]) -> int:
    """Write each record (with ``benchmark.object/seed/method``) that matches a job without a
    result yet as that job's result.json, noting ``imported_from``; returns how many."""
    wanted = dict(jobs)
    count = 0
    for rec in records:
        b = rec["benchmark"]
        run_dir = wanted.get((b["object"], b["seed"], b["method"]))
        if run_dir is None or (Path(run_dir) / RESULT_FILE).is_file():
            continue
        write_result(run_dir, {**rec, "imported_from": str(path)})
        count += 1
    return count
