"""``mvtop estimate``: run the M-VTOP estimator (``estimator``) over a log and write the pose track.

This module only wires io to the estimator: it maps the config to the log's topics, reads
the frames (``io.frames``), steps the ``Estimator`` through them with a checkpoint of every
completed frame (``checkpoint``), and writes the outputs (``track``).
"""

from __future__ import annotations

import contextlib
import signal
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

from ..config import Config
from ..errors import EstimationError
from ..estimator import Estimator, SceneModel
from ..io.frames import FrameReader, LogTopics, SensorTopics
from ..io.mcap_reader import McapLog
from ..records import Frame
from .checkpoint import Checkpoint, EstimateInterrupted, Restored, fingerprint
from .debug_images import frame_masks
from .track import run_summary, stage_timing, write_track


@dataclass(frozen=True)
class EstimateOptions:
    """Command-line overrides of the config."""

    modalities: tuple[str, ...] | None = None
    num_particles: int | None = None
    seed: int | None = None
    max_frames: int | None = None
    debug_images: bool = False  # each sensor's observed and rendered masks in track.mcap (debug_images)


def sensor_topics(cfg: Config) -> list[SensorTopics]:
    """The reader's view of the config's sensors (honouring the enabled modalities)."""
    out = []
    if "vision" in cfg.modalities:
        out += [SensorTopics(c.name, "camera", c.image_topic, c.info_topic, None, c.frame, c.mask_topic)
                for c in cfg.sensors.cameras]
    if "tactile" in cfg.modalities:
        out += [
            SensorTopics(t.name, "tactile", t.image_topic, t.info_topic, t.depth_topic, t.frame)
            for t in cfg.sensors.tactile
        ]
    return out


def log_topics(cfg: Config) -> LogTopics:
    """The non-image topics the frames read. The contact signal (``topics.contact``, else the
    force of ``topics.wrench``) is read whenever the log holds it, whatever the modalities: it
    is the motion model's input c_k (Algorithm 3-4) in every method; the ``contact`` modality
    adds the contact likelihood (eq. 8-9) and makes the signal required (``Config.required_topics``)."""
    t = cfg.topics
    return LogTopics(
        tf=t.tf, tf_static=t.tf_static, contact=t.contact,
        joint_states=t.joint_states, ground_truth=t.ground_truth, world_frame=cfg.frames.world,
        ee_frame=cfg.frames.ee, sync_tolerance_ns=int(round(cfg.sync_tolerance_s * 1e9)),
        wrench=t.wrench,
        contact_force_on_n=cfg.contact.force_on_n, contact_force_off_n=cfg.contact.force_off_n,
        urdf=None if cfg.robot.urdf is None else str(cfg.robot.urdf),
    )


def apply_options(cfg: Config, options: EstimateOptions) -> Config:
    """The config with the command line's overrides applied."""
    if options.modalities is not None:
        cfg = replace(cfg, modalities=tuple(options.modalities))
    f = cfg.filter
    if options.num_particles is not None:
        f = replace(f, num_particles=options.num_particles)
    if options.seed is not None:
        f = replace(f, seed=options.seed)
    return replace(cfg, filter=f)


def estimate(
    log_path: Path, cfg: Config, out_dir: Path, options: EstimateOptions = EstimateOptions(),
    progress: Callable[[int, int], None] | None = None, *, resume: bool = False,
) -> dict:
    """Run the filter over ``log_path`` and write track.mcap, track.csv, summary.json and
    config.resolved.yaml into ``out_dir``; returns the summary.

    Every completed frame is checkpointed in ``out_dir/.mvtop-checkpoint`` (see
    ``checkpoint``) and its result kept there, not in memory. ``resume`` continues from that
    checkpoint's last frame (the outputs are those of an uninterrupted run with the same seed);
    without it an existing checkpoint is discarded. The checkpoint is removed once the outputs
    are written, and when a fresh run fails (a resumed run keeps it). With
    ``options.debug_images`` each frame's observed and rendered masks are journaled with its
    result and written to track.mcap (``debug_images``). Ctrl-C or
    ``checkpoint.Terminated`` (SIGTERM) raise ``checkpoint.EstimateInterrupted`` saying how
    many frames are checkpointed.
    """
    cfg = apply_options(cfg, options)
    t_start = time.perf_counter()
    sensors = sensor_topics(cfg)
    if not sensors and "contact" not in cfg.modalities:
        raise EstimationError("no sensor is enabled: check modalities and sensors in the config")
    fp = {**fingerprint(log_path, cfg), "options": {"debug_images": bool(options.debug_images)}}
    # A resumed run checks its checkpoint first (missing, or another run's: one line at once);
    # a fresh run starts one once its inputs have loaded, and removes it on an error.
    ck, restored = Checkpoint.start(out_dir, fp, resume=True) if resume else (None, None)
    created = False
    total = 0
    try:
        scene = SceneModel(cfg, build_contact="contact" in cfg.modalities)
        with McapLog(log_path) as log:
            reader = FrameReader(log, sensors, log_topics(cfg))
            total = _count_frames(log, sensors, options.max_frames)
            estimator = Estimator(cfg, scene, lambda frame, t: reader.tf.lookup(cfg.frames.world, frame, t))
            startup_s = time.perf_counter() - t_start
            if ck is None:
                created = not out_dir.exists()
                out_dir.mkdir(parents=True, exist_ok=True)
                ck, restored = Checkpoint.start(out_dir, fp, resume=False)
            _run_frames(reader, estimator, ck, restored, options.max_frames, total, progress, t_start,
                        options.debug_images)
            skipped = list(reader.skipped)
            if not ck.frames_done:
                raise EstimationError(f"{log_path}: no frame with the configured sensors could be read")
    except KeyboardInterrupt as err:
        if ck is None:
            raise
        ck.close()
        saved = ck.saved_frames()  # the state on disk, which a signal may have left one frame ahead
        if not saved and not resume:  # nothing to resume: leave nothing behind
            ck.remove()
            if created:
                _remove_if_empty(out_dir)
        raise EstimateInterrupted(saved, total, ck.dir, "frames", _signum(err)) from None
    except BaseException:
        if ck is not None and not resume:
            ck.remove()
        if created:
            _remove_if_empty(out_dir)
        if ck is not None:
            ck.close()
        raise
    elapsed = restored.elapsed_s + time.perf_counter() - t_start
    results = ck.results(options.max_frames)
    try:
        summary = run_summary(results, cfg, log_path, elapsed, skipped, scene.warnings)
        summary["resumed_at_frame"] = restored.frames_done
        summary["checkpoint_ms_per_frame"] = round(1e3 * ck.write_seconds / max(ck.writes, 1), 3)
        summary["timing"] = stage_timing(results, startup_s)
        write_track(out_dir, results, cfg, summary)
    except KeyboardInterrupt as err:
        ck.close()
        raise EstimateInterrupted(len(results), total, ck.dir, "outputs", _signum(err)) from None
    ck.remove()
    return summary


def _run_frames(reader: FrameReader, estimator: Estimator, ck: Checkpoint, restored: Restored,
                max_frames: int | None, total: int, progress: Callable[[int, int], None] | None,
                t_start: float, debug_images: bool = False) -> None:
    """The frame loop: replay the ``restored.frames_done`` frames a resumed run has done
    (the reader's grouping and skip list, the tactile reference images and the mode check's
    earlier frames come out as in the first run), restore the particles and the generator,
    then step the filter and checkpoint each further frame (with ``debug_images``, with its
    sensors' masks)."""
    done = restored.frames_done
    if restored.particles is not None:
        estimator.particles = restored.particles
    if restored.rng_state is not None:
        estimator.rng.bit_generator.state = restored.rng_state  # the filter's generator too (one object)
    if done:  # the state the last completed frame carried over, kept in its journal record
        estimator.resume_after(ck.results()[done - 1])
    if progress is not None:  # at once, from the resumed frame (0 for a fresh run)
        progress(min(done, total), total)
    primed: set[str] = set()
    n = 0
    frames = iter(reader)
    while True:
        t_read = time.perf_counter()
        frame = next(frames, None)
        if frame is None:
            break
        if n < done:
            _prime_observer(estimator, frame, primed)
            estimator.remember(frame)
        else:
            read_s = time.perf_counter() - t_read
            result = estimator.step(frame)
            result.timings["read_s"] = read_s
            if debug_images and result.sensors:
                ids = {n: reader.sensor_frame(n) or f"{n}_sensor" for n in result.sensors}
                result = replace(result, debug_masks=frame_masks(estimator, frame, result, ids))
            ck.record(result, estimator.particles, estimator.rng, restored.elapsed_s + time.perf_counter() - t_start)
            if progress is not None:
                progress(n + 1, total)
        n += 1
        if max_frames is not None and n >= max_frames:
            break


def _prime_observer(estimator: Estimator, frame: Frame, primed: set[str]) -> None:
    """On a replayed frame, let the observer see each tactile sensor's first image: the
    colour-difference masks use it as the no-contact reference (see ``Observer``)."""
    for name, img in frame.tactile.items():
        if name not in primed:
            primed.add(name)
            if img.depth is None:
                estimator.observer.tactile_mask(img)


def _signum(err: BaseException) -> int:
    return int(getattr(err, "signum", signal.SIGINT))


def _remove_if_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):
        folder.rmdir()


def _count_frames(log: McapLog, sensors: list[SensorTopics], max_frames: int | None) -> int:
    counts = [
        log.summary().topic(s.image_topic).message_count for s in sensors if log.summary().has_topic(s.image_topic)
    ]
    n = max(counts) if counts else 0
    return min(n, max_frames) if max_frames else n
