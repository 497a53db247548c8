"""The ``mvtop`` command line: click commands only; pipelines do the work, this module prints."""

from __future__ import annotations

import contextlib
import shlex
import signal
import sys
import time
from pathlib import Path

import click

from . import __version__
from .durations import format_duration
from .errors import MvtopError

LOG_PATH = click.Path(exists=False, dir_okay=True, path_type=Path)
CONFIG_OPTION = click.option(
    "--config", "-c", "config_path", type=click.Path(dir_okay=False, path_type=Path),
    help="YAML config describing the object, environment and sensors (see configs/).",
)


def particles_option(default: int | None = None, what: str = "Particles"):
    """``--particles N``: the filter's particle count (default: the config's, or ``default``)."""
    if default is None:
        return click.option("--particles", type=click.IntRange(10, 1_000_000), help=f"{what} (default: the config's).")
    return click.option("--particles", type=click.IntRange(10, 1_000_000), default=default, show_default=True,
                        help=f"{what}.")


def seed_option(default: int | None = None, what: str = "Random seed"):
    """``--seed N``: the seed of a random process (default: the config's, or ``default``)."""
    if default is None:
        return click.option("--seed", type=click.IntRange(min=0),
                            help=f"{what} (default: the config's): same seed, same outputs.")
    return click.option("--seed", type=click.IntRange(min=0), default=default, show_default=True,
                        help=f"{what}: same seed, same outputs.")


class _Group(click.Group):
    """Lists commands in the order they were added (the order of a typical session)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="mvtop")
def cli() -> None:
    """Estimate the 6D pose of an object held in a robot gripper from ROS 2 MCAP logs.

    mvtop fuses RGB cameras, GelSight-style tactile sensors and a contact signal with a
    render-and-compare particle filter (M-VTOP). A typical session:

    \b
      mvtop simulate --object cube --seed 1 --out cube.mcap   # a log with ground truth
      mvtop inspect cube.mcap --config configs/cube.yaml      # what is in it, what is missing
    """


@cli.command("inspect")
@click.argument("log", type=LOG_PATH)
@CONFIG_OPTION
def inspect_cmd(log: Path, config_path: Path | None) -> None:
    """Show the topics, types, counts, rates and time range of LOG (an .mcap file or a rosbag2
    folder). With --config, check that every topic and TF frame the config needs is present."""
    from .pipelines.inspect import format_report, inspect_log

    required_topics = required_frames = urdf = gt_topic = None
    world = "world"
    if config_path is not None:
        from .config import load_config

        cfg = load_config(config_path)
        required_topics, required_frames, urdf = cfg.required_topics(), cfg.required_frames(), cfg.robot.urdf
        gt_topic, world = cfg.topics.ground_truth, cfg.frames.world
    report = inspect_log(log, required_topics=required_topics, required_frames=required_frames, urdf=urdf,
                         ground_truth_topic=gt_topic, world_frame=world)
    click.echo(format_report(report))
    problems = []
    if report.missing_topics:
        problems.append("missing topics " + ", ".join(report.missing_topics))
    if report.wrong_types:
        problems.append("wrong types " + ", ".join(f"{t} (expected {e}, found {a})" for t, e, a in report.wrong_types))
    if report.empty_topics:
        problems.append("topics without messages " + ", ".join(report.empty_topics))
    if report.missing_frames:
        problems.append("missing TF frames " + ", ".join(report.missing_frames))
    if report.summary.truncated_at is not None:
        cut_file, cut_at = report.summary.truncated_at
        problems.append(f"{cut_file.name} is truncated at byte {cut_at} (expected a complete file with its footer)")
    if report.ground_truth is not None and not report.ground_truth.connected:
        problems.append(report.ground_truth.problem())
    if problems:
        raise MvtopError(f"{log}: " + "; ".join(problems))


@contextlib.contextmanager
def _progress(label: str, resumable: bool = False):
    """Progress on stderr; yields ``update(done, total)``. On a terminal, a progress bar; else
    (a log file, a CI job) a plain line at most every ``_PLAIN_PROGRESS_INTERVAL_S`` seconds, and
    one when work that took longer than that is complete, with the time elapsed and an estimate
    of the time left, at the rate since the first unit of work done in this run (the first
    frame compiles the kernels and searches the whole grasp prior: it would put the estimate
    an order of magnitude too high), so none before a second unit is done.

    With ``resumable``, a first update that already reports work done (a resumed run) makes
    the bar count from there: it shows ``done/total`` and an ETA from the remaining work only
    (the plain lines always estimate from the work done in this run)."""
    bar = None
    start = 0
    plain = {"t0": None, "first": 0, "last": 0.0, "t1": None, "one": 0}

    def plain_line(done: int, total: int) -> None:
        now = time.monotonic()
        if plain["t0"] is None:
            plain["t0"], plain["first"], plain["last"] = now, done, now
            return
        if plain["t1"] is None and done > plain["first"]:  # the run's first unit: the rate starts here
            plain["t1"], plain["one"] = now, done
        finished_long = done >= total and now - plain["t0"] >= _PLAIN_PROGRESS_INTERVAL_S
        if now - plain["last"] < _PLAIN_PROGRESS_INTERVAL_S and not finished_long:
            return  # short jobs print no progress at all, long ones a line a minute and the last
        plain["last"] = now
        elapsed = now - plain["t0"]
        since = now - plain["t1"] if plain["t1"] is not None else 0.0
        rate = (done - plain["one"]) / since if since > 0 else 0.0
        left = "" if done >= total or rate <= 0 else f", about {format_duration((total - done) / rate)} left"
        pct = 100.0 * done / max(total, 1)
        click.echo(f"{label}: {done}/{total} ({pct:.0f} %), {format_duration(elapsed)} elapsed{left}", err=True)

    def update(done: int, total: int) -> None:
        nonlocal bar, start
        if not sys.stderr.isatty():
            plain_line(done, total)
            return
        if bar is None:
            start = done if resumable else 0
            if start:
                bar = click.progressbar(length=max(total - start, 1), label=f"{label} (resumed)", file=sys.stderr,
                                        show_percent=False, show_eta=True, item_show_func=lambda item: item)
                bar.current_item = f"{done}/{total}"
            else:
                bar = click.progressbar(length=total, label=label, file=sys.stderr, show_pos=True, show_eta=True)
            bar.__enter__()
        bar.update(done - start - bar.pos, f"{done}/{total}" if start else None)

    try:
        yield update
    finally:
        if bar is not None:
            bar.__exit__(None, None, None)


# Seconds between two plain progress lines when stderr is not a terminal: often enough to
# show that a long job (a benchmark of hours) is alive, rarely enough to keep logs short.
_PLAIN_PROGRESS_INTERVAL_S = 60.0


@contextlib.contextmanager
def _sigterm_interrupts():
    """While the body runs, SIGTERM raises ``checkpoint.Terminated`` (a KeyboardInterrupt) in
    the main thread, so a terminated run cleans up and reports like Ctrl-C."""
    from .pipelines.checkpoint import Terminated

    def handler(signum, _frame):
        raise Terminated(signum)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _signal_name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


@contextlib.contextmanager
def _stops_resumably(label: str, out_dir: Path, finished: str):
    """A job of many runs (a batch, a benchmark) stopped by Ctrl-C or SIGTERM: its worker
    processes are stopped (``batch.engine``), the runs it finished stay in ``out_dir`` (each
    written whole), and one line says so; exit code 128 + the signal's number."""
    try:
        with _sigterm_interrupts():
            yield
    except KeyboardInterrupt as stop:
        signum = int(getattr(stop, "signum", signal.SIGINT))
        click.echo(f"mvtop: {label} interrupted ({_signal_name(signum)}); the {finished} it finished are kept in "
                   f"{out_dir}: run the same command to go on", err=True)
        sys.exit(128 + signum)


def _check_output_path(out: Path, suffix: str | None = None) -> None:
    if suffix and out.suffix != suffix:
        raise MvtopError(f"{out}: expected an output file name ending in {suffix}")
    if not out.parent.exists():
        raise MvtopError(f"{out}: the output folder {out.parent} does not exist")


@cli.command("simulate")
@click.option("--object", "object_name", metavar="NAME", help="Object to simulate (see --list).")
@click.option("--object-file", "object_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Simulate your own part: an object file (YAML, README \"Your own part\"; mvtop mesh-check "
                   "writes one).")
@seed_option(0)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), help="Output log (.mcap).")
@click.option("--frames", type=click.IntRange(4, 100000), default=30, show_default=True, help="Frames at 10 Hz.")
@click.option("--grasp-translation-mm", type=click.FloatRange(0, 20), default=3.0, show_default=True,
              help="Half-width of the uniform in-hand offset along the ee x and z axes.")
@click.option("--grasp-rotation-deg", type=click.FloatRange(0, 90), default=10.0, show_default=True,
              help="Half-width of the in-hand rotation about the pad normal.")
@click.option("--grasp-tilt-deg", type=click.FloatRange(0, 30), default=2.0, show_default=True,
              help="Half-width of the tilt about the other two axes (the pads flatten it).")
@click.option("--slip-mm", type=click.FloatRange(0, 5), default=0.1, show_default=True,
              help="Std of the in-hand slip per frame in contact.")
@click.option("--slip-deg", type=click.FloatRange(0, 10), default=0.2, show_default=True,
              help="Std of the rotational slip per frame in contact.")
@click.option("--occluders", type=click.IntRange(0, 10), default=0, show_default=True,
              help="Extra cables hanging in front of the object (unknown to the estimator).")
@click.option("--exposure-jitter", type=click.FloatRange(0, 2), default=0.0, show_default=True,
              help="Std of the per-frame log exposure (lighting changes).")
@click.option("--low-contrast", is_flag=True, help="Paint the object like the gripper (the paper's peg).")
@click.option("--object-color", metavar="R,G,B", help="Paint the object this colour (0-1 each), e.g. 1,0,1.")
@click.option("--distortion", metavar="K1,K2,P1,P2,K3",
              help="Camera lens distortion (plumb_bob), e.g. -0.15,0.05,0,0,0.")
@click.option("--noise", type=click.FloatRange(0, 50), default=2.0, show_default=True, help="Camera read noise [DN].")
@click.option("--resolution", default="640x480", show_default=True, metavar="WxH", help="Camera resolution.")
@click.option("--image-format", type=click.Choice(["jpeg", "png", "raw"]), default="jpeg", show_default=True,
              help="Camera images: sensor_msgs/CompressedImage (jpeg, png) on .../image/compressed, or raw "
                   "sensor_msgs/Image rgb8 on .../image.")
@click.option("--tactile-format", type=click.Choice(["jpeg", "png", "raw"]), default="jpeg", show_default=True,
              help="Tactile images, as --image-format.")
@click.option("--jpeg-quality", type=click.IntRange(10, 100), default=90, show_default=True)
@click.option("--kinematics", type=click.Choice(["ee-tf", "tf-chain", "joint-states"]), default="ee-tf",
              show_default=True,
              help="How the log gives the end effector: ee-tf one world->ee transform; tf-chain a gantry robot's TF "
                   "tree (world -> base_link -> six moving links -> flange -> tool0 -> ee); joint-states only "
                   "/joint_states, with the robot's URDF written by --write-config (robot.urdf).")
@click.option("--camera-every", type=click.IntRange(1, 10), default=1, show_default=True,
              help="Cameras capture on every N-th frame only (2: half the tactile rate).")
@click.option("--drop-fraction", type=click.FloatRange(0, 0.9), default=0.0, show_default=True,
              help="Fraction of images lost at random (seeded), each camera and tactile image independently.")
@click.option("--stamp-jitter-ms", type=click.FloatRange(0, 10), default=0.0, show_default=True,
              help="Each sensor captures (and stamps) its image up to +-this far from the frame's time "
                   "(within the config's default sync_tolerance_s of 20 ms).")
@click.option("--compression", type=click.Choice(["zstd", "lz4", "none"]), default="zstd", show_default=True,
              help="MCAP chunk compression.")
@click.option("--mask-topics", type=click.Choice(["raw", "png"]), default=None,
              help="Also record each camera's true object mask, as an external segmenter would publish it: raw "
                   "sensor_msgs/Image mono8 on /cameras/NAME/mask, or png on /cameras/NAME/mask/compressed (255 = "
                   "object); --write-config then reads them (masking.camera.backend: topic).")
@click.option("--mask-error-px", type=click.IntRange(0, 50), default=0, show_default=True,
              help="Degrade the recorded masks: grow or shrink each by a random 0 to this many pixels.")
@click.option("--scene", type=click.Choice(["default", "hard"]), default="default", show_default=True,
              help="hard: every option below on, and --exposure-jitter 0.1.")
@click.option("--shadows", is_flag=True, help="A key light that casts shadows; dim ambient light leaves faces dark.")
@click.option("--glossy", is_flag=True, help="Polished plastic object with specular highlights.")
@click.option("--clutter", is_flag=True, help="Textured table and board, boxes and cylinders around the board.")
@click.option("--light-change", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Lighting that changes between frames: the key light turns by about 30x this [deg] and the "
                   "lights dim or brighten by exp(N(0, this)).")
@click.option("--write-config", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the YAML config that pairs with the log, the meshes in meshes/ beside it and, with "
                   "--kinematics joint-states, the robot's URDF beside it.")
@click.option("--list", "list_objects", is_flag=True, help="List the objects and exit.")
def simulate_cmd(object_name, object_file, seed, out, frames, grasp_translation_mm, grasp_rotation_deg, grasp_tilt_deg,
                 slip_mm,
                 slip_deg, occluders, exposure_jitter, low_contrast, object_color, distortion, noise, resolution,
                 image_format, tactile_format,
                 jpeg_quality, kinematics, camera_every, drop_fraction, stamp_jitter_ms, compression, mask_topics,
                 mask_error_px, scene, shadows, glossy, clutter, light_change, write_config,
                 list_objects) -> None:
    """Simulate a visuo-tactile insertion episode and write it as a ROS 2 MCAP log with ground truth.

    The object is grasped with a random in-hand offset, carried above its receptacle and lowered
    until it touches; two RGB cameras, two GelSight-like tactile sensors, TF, joint states, the
    contact flag, the wrench and the ground-truth object pose are recorded at 10 Hz.

    To check a setup like yours, record the way it does: --image-format raw, --distortion,
    --kinematics tf-chain or joint-states, --camera-every, --drop-fraction, --stamp-jitter-ms
    (docs/recording.md); --write-config writes the config that reads such a log. --scene hard
    (or --shadows, --glossy, --clutter, --light-change) makes harder camera images; --mask-topics
    records object masks as a segmentation node on the robot would.
    """
    from .sim.objects import get_object
    from .sim.objects import list_objects as names

    if list_objects:
        for n in names():
            click.echo(f"{n:<10} {get_object(n).description}")
        return
    if object_name and object_file:
        raise MvtopError("simulate takes --object NAME or --object-file FILE, not both")
    if not (object_name or object_file) or out is None:
        raise MvtopError("simulate needs --object NAME (or --object-file FILE) and --out PATH.mcap (or --list)")
    try:
        width, height = (int(v) for v in resolution.lower().split("x"))
    except ValueError:
        raise MvtopError(f"--resolution: expected WxH such as 640x480, got {resolution!r}") from None
    if not (64 <= width <= 4096 and 48 <= height <= 4096):
        raise MvtopError(f"--resolution: expected 64-4096 x 48-4096 pixels, got {resolution!r}")
    rgb = None
    if object_color:
        try:
            rgb = tuple(float(v) for v in object_color.split(","))
        except ValueError:
            rgb = ()
        if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
            raise MvtopError(f"--object-color: expected three numbers 0-1 such as 1,0,1, got {object_color!r}")
    dist = None
    if distortion:
        try:
            dist = tuple(float(v) for v in distortion.split(","))
        except ValueError:
            dist = ()
        if len(dist) != 5:
            raise MvtopError(f"--distortion: expected five numbers k1,k2,p1,p2,k3, got {distortion!r}")
    _check_output_path(out, ".mcap")
    from .pipelines.simulate import SimulateOptions, scene_options, simulate, write_scene_config
    from .sim.episode import EpisodeOptions
    from .sim.timing import SensorTiming

    if object_file is not None:
        from .sim.object_file import load_object_file

        object_name = load_object_file(object_file)  # a bad file fails before any work
    else:
        get_object(object_name)  # unknown names fail before any work
    options = SimulateOptions(
        episode=EpisodeOptions(
            frames=frames, grasp_translation_m=grasp_translation_mm / 1000.0, grasp_rotation_deg=grasp_rotation_deg,
            grasp_tilt_deg=grasp_tilt_deg, slip_translation_m=slip_mm / 1000.0, slip_rotation_deg=slip_deg,
        ),
        width=width, height=height, noise_std=noise, exposure_jitter=exposure_jitter, low_contrast=low_contrast,
        object_rgb=rgb, distortion=dist,
        occluders=occluders, image_format=image_format, tactile_format=tactile_format, jpeg_quality=jpeg_quality,
        compression=compression, kinematics=kinematics,
        timing=SensorTiming(camera_every=camera_every, drop_fraction=drop_fraction, jitter_s=stamp_jitter_ms / 1000.0),
        mask_topics=mask_topics is not None, mask_format=mask_topics or "raw", mask_error_px=mask_error_px,
        shadows=shadows, glossy=glossy, clutter=clutter, light_change=light_change,
    )
    options = scene_options(options, scene)
    with _progress(f"simulate {getattr(object_name, 'name', object_name)}") as update:
        summary = simulate(object_name, seed, out, options, progress=update)
    click.echo(f"wrote {summary.path}: {summary.frames} frames ({summary.contact_frames} in contact), "
               f"{summary.bytes / 1e6:.1f} MB")
    if write_config is not None:
        write_scene_config(object_name, write_config, options)
        click.echo(f"wrote {write_config}")


@cli.command("mesh-check")
@click.argument("mesh", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--receptacle", type=click.Path(dir_okay=False, path_type=Path),
              help="The receptacle's mesh: also measure the insertion depth and the clearance per direction.")
@click.option("--units", type=click.Choice(["auto", "m", "mm"]), default="auto", show_default=True,
              help="Units of the mesh files (auto: from the size).")
@click.option("--leading-face", type=click.Choice(["-z", "+z", "-x", "+x", "-y", "+y", "cad"]), default="-z",
              show_default=True, help="The face of the part's bounding box that enters the receptacle first "
                                      "(cad: the file is in mvtop's object frame already).")
@click.option("--mouth", type=click.Choice(["+z", "-z", "-x", "+x", "-y", "+y", "cad"]), default="+z",
              show_default=True, help="The face of the receptacle's bounding box that holds the mouth.")
@click.option("--max-faces", type=click.IntRange(100, 10_000_000), default=5000, show_default=True,
              help="Finer meshes get a simplified copy for the renderer.")
@click.option("--symmetry-tolerance-mm", type=click.FloatRange(0, 10, min_open=True), default=0.02, show_default=True,
              help="A transform is a symmetry when it moves every test point at most this far off the surface.")
@click.option("--name", help="Object name (default: the mesh file's stem).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the object file here (and the renderer's copy beside it); default: print it.")
def mesh_check_cmd(mesh: Path, receptacle: Path | None, units: str, leading_face: str, mouth: str, max_faces: int,
                   symmetry_tolerance_mm: float, name: str | None, out: Path | None) -> None:
    """Check a part's CAD file (and its receptacle's) and describe it as an object file.

    One line per finding: units from the size, watertightness and repairs, face count (with a
    simplified copy for the renderer), the symmetries found numerically, and with --receptacle
    the insertion depth and the clearance per direction at the inserted pose. The output is an
    object file for mvtop simulate --object-file and mvtop benchmark accuracy --object-file.
    """
    from .sim.mesh_check import CheckOptions, check, write_result

    if out is not None:
        _check_output_path(out, ".yaml")
    options = CheckOptions(units=units, leading_face=leading_face, mouth=mouth, max_faces=max_faces,
                           symmetry_tolerance_m=symmetry_tolerance_mm / 1000.0, name=name)
    result = check(mesh, receptacle, options)
    text = write_result(result, out)
    if out is None:
        click.echo(text, nl=False)
    else:
        for line in result.findings:
            click.echo(line)
        click.echo(f"wrote {out}")


@cli.command("estimate")
@click.argument("log", nargs=-1, type=LOG_PATH)
@CONFIG_OPTION
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder: track.mcap, track.csv, summary.json, config.resolved.yaml (several logs: "
                   "one folder per log in it, and runs.csv).")
@click.option("--modalities", metavar="LIST",
              help="Comma-separated subset of vision,tactile,contact (default: the config's); contact adds "
                   "the contact likelihood, while the log's contact signal sets the motion noise in any case.")
@particles_option(what="Number of particles")
@seed_option()
@click.option("--max-frames", type=click.IntRange(min=1), help="Stop after this many frames.")
@click.option("--resume", is_flag=True,
              help="Continue an interrupted run from the checkpoint in --out, after its last completed frame "
                   "(same log, config and options needed; the track is that of an uninterrupted run). Without "
                   "--resume a checkpoint left in --out is discarded and the run starts at the first frame.")
@click.option("--manifest", type=click.Path(dir_okay=False, path_type=Path),
              help="CSV or YAML table of logs to estimate: columns log, config, seed, modalities, particles, "
                   "max_frames, name (see README.md, Many logs).")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Several logs: parallel worker processes on this machine (with --ray local: its CPUs).")
@click.option("--ray", "ray_address", metavar="ADDRESS",
              help="Several logs: run them as Ray tasks: local (a Ray instance on this machine), auto (the cluster "
                   "this machine joined with `ray start`) or a cluster address HOST:PORT. Needs the ray extra.")
@click.option("--debug-images", is_flag=True,
              help="Also write each sensor's observed mask and the mask rendered at the estimate to track.mcap "
                   "(/mvtop/debug/SENSOR/observed and /rendered, mono8 images; README.md, Outputs). One log only.")
def estimate_cmd(log: tuple[Path, ...], config_path: Path | None, out_dir: Path, modalities: str | None,
                 particles: int | None, seed: int | None, max_frames: int | None, resume: bool,
                 manifest: Path | None, workers: int, ray_address: str | None, debug_images: bool) -> None:
    """Estimate the object's pose in every frame of LOG and write the pose track to --out.

    Runs the M-VTOP particle filter: object masks from every camera and tactile image,
    render-and-compare scoring of each pose particle, the contact likelihood, and the
    weighted-mean estimate (see README.md for what is done beyond the paper).

    Every completed frame is checkpointed in --out/.mvtop-checkpoint (removed when the run
    completes). Stopped by Ctrl-C or SIGTERM, the run leaves no partly written output, says
    how many frames are checkpointed and exits with 130 (Ctrl-C) or 143 (SIGTERM); add
    --resume to the same command to continue (docs/long-runs.md).

    Several LOGs, a folder of logs, a glob pattern or --manifest: each log is estimated into
    a folder of its own in --out, on --workers processes or Ray tasks (--ray), and OUT/runs.csv
    gets a row per log; running the same command again skips the logs already done.
    """
    from .batch.jobs import is_batch_input
    from .config import MODALITIES, load_config
    from .pipelines.estimate import EstimateOptions, estimate

    if manifest is not None or len(log) != 1 or is_batch_input(log[0]):
        if debug_images:
            raise MvtopError("--debug-images works with a single LOG (run it on the log whose masks you want to see)")
        _estimate_many(log, manifest, config_path, out_dir, modalities, particles, seed, max_frames, workers,
                       ray_address)
        return
    log = log[0]
    if config_path is None:
        raise MvtopError("estimate needs --config CFG (see configs/)")
    cfg = load_config(config_path)
    mods = None
    if modalities:
        mods = tuple(m.strip() for m in modalities.split(",") if m.strip())
        bad = [m for m in mods if m not in MODALITIES]
        if bad or not mods:
            raise MvtopError(f"--modalities: expected a comma-separated subset of {','.join(MODALITIES)}, "
                             f"got {modalities!r}")
    if out_dir.exists() and not out_dir.is_dir():
        raise MvtopError(f"{out_dir}: exists and is not a folder")
    options = EstimateOptions(modalities=mods, num_particles=particles, seed=seed, max_frames=max_frames,
                              debug_images=debug_images)
    from .pipelines.checkpoint import EstimateInterrupted

    again = ["mvtop", "estimate", str(log), "--config", str(config_path), "--out", str(out_dir)]
    for flag, value in (("--modalities", modalities), ("--particles", particles), ("--seed", seed),
                        ("--max-frames", max_frames)):
        if value is not None:
            again += [flag, str(value)]
    if debug_images:
        again.append("--debug-images")
    try:
        with _sigterm_interrupts(), _progress(f"estimate {log.name}", resumable=True) as update:
            summary = estimate(log, cfg, out_dir, options, progress=update, resume=resume)
    except EstimateInterrupted as stop:
        how = _signal_name(stop.signum)
        if stop.frames_done == 0:
            click.echo(f"mvtop: interrupted ({how}) before the first frame was completed; nothing to resume: "
                       "run the same command again", err=True)
        else:
            where = (f"while writing the outputs; all {stop.frames_done} frames are checkpointed in"
                     if stop.phase == "outputs" else
                     f"after {stop.frames_done} of {stop.total} frames; checkpoint in")
            click.echo(f"mvtop: interrupted ({how}) {where} {stop.checkpoint_dir}; resume with: "
                       f"{shlex.join(again + ['--resume'])}", err=True)
        sys.exit(128 + stop.signum)
    except KeyboardInterrupt as stop:  # before the run's checkpoint existed
        signum = int(getattr(stop, "signum", signal.SIGINT))
        click.echo(f"mvtop: interrupted ({_signal_name(signum)}) before the first frame was completed; nothing to "
                   "resume: run the same command again", err=True)
        sys.exit(128 + signum)
    f = summary["final"]
    line = (f"wrote {out_dir}: {summary['frames_processed']} frames in {summary['run_time_s']:.1f} s; final spread "
            f"{1000 * f['translation_std_m']:.3f} mm, {f['rotation_std_deg']:.2f} deg")
    if "ground_truth_translation_error_mm" in f:
        line += (f"; error vs ground truth {f['ground_truth_translation_error_mm']:.3f} mm, "
                 f"{f['ground_truth_rotation_error_deg']:.2f} deg")
    click.echo(line)
    from .pipelines.track import warning_report

    for line in warning_report(summary):  # one line per kind of failure (summary.json has every frame)
        click.echo(f"mvtop: warning: {line} (see summary.json)", err=True)


def _estimate_many(logs: tuple[Path, ...], manifest: Path | None, config_path: Path | None, out_dir: Path,
                   modalities: str | None, particles: int | None, seed: int | None, max_frames: int | None,
                   workers: int, ray_address: str | None) -> None:
    """``mvtop estimate`` over several logs (see batch/): the job list, the batch with its
    progress, the summary line, and a line per failed log; exit code 1 when a log failed."""
    from .batch.engine import make_engine
    from .batch.jobs import jobs_from_arguments, jobs_from_manifest, parse_modalities
    from .batch.run import format_summary, run_batch
    from .config import load_config

    if manifest is not None and logs:
        raise MvtopError("give either LOG arguments or --manifest, not both")
    if manifest is None and not logs:
        raise MvtopError("estimate needs a LOG (or several, a folder, a glob pattern) or --manifest FILE")
    defaults = {"modalities": None if not modalities else parse_modalities(modalities, "--modalities"),
                "particles": particles, "seed": seed, "max_frames": max_frames}
    jobs = (jobs_from_manifest(manifest, config_path, out_dir, defaults) if manifest is not None
            else jobs_from_arguments([str(p) for p in logs], config_path, out_dir, defaults))
    for cfg in sorted({j.config for j in jobs}):  # a bad config stops the batch before any work
        load_config(cfg)
    engine = make_engine(workers, ray_address)
    with _stops_resumably("estimate", out_dir, "logs"), _batch_progress("estimate") as update:
        summary = run_batch(jobs, out_dir, engine, progress=update)
    click.echo(format_summary(summary))
    failed = [r for r in summary["records"] if r["status"] != "ok"]
    for r in failed if sys.stderr.isatty() else []:  # (in a log, each failure had its line when it happened)
        click.echo(f"mvtop: {r['name']} failed: {r['error']}", err=True)
    if failed:
        click.echo(f"mvtop: error: {len(failed)} of {len(jobs)} logs failed (see {summary['table']})", err=True)
        sys.exit(1)


@contextlib.contextmanager
def _batch_progress(label: str):
    """Progress of a batch on stderr; yields ``update(BatchProgress)``. On a terminal a bar
    (logs done, failed, time left); else a line per failed log and a progress line at most
    every ``_PLAIN_PROGRESS_INTERVAL_S`` seconds, and at the end."""
    from .batch.run import format_progress

    state = {"bar": None, "start": 0, "last": time.monotonic()}

    def update(p) -> None:
        if not sys.stderr.isatty():
            now = time.monotonic()
            if p.last is not None and p.last.get("status") != "ok":
                click.echo(f"{label}: {p.last['name']} failed: {p.last.get('error')}", err=True)
            if (p.done >= p.total and p.done > p.skipped) or now - state["last"] >= _PLAIN_PROGRESS_INTERVAL_S:
                state["last"] = now
                click.echo(format_progress(p, label), err=True)
            return
        if state["bar"] is None:
            state["start"] = p.skipped
            state["bar"] = click.progressbar(length=max(p.total - p.skipped, 1), label=f"{label} {p.total} logs",
                                             file=sys.stderr, show_eta=True, show_percent=False,
                                             item_show_func=lambda item: item)
            state["bar"].__enter__()
        failed = f", {p.failed} failed" if p.failed else ""
        state["bar"].update(p.done - state["start"] - state["bar"].pos, f"{p.done}/{p.total} done{failed}")

    try:
        yield update
    finally:
        if state["bar"] is not None:
            state["bar"].__exit__(None, None, None)


@cli.command("eval")
@click.argument("track_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--log", "log_path", type=LOG_PATH, help="The log the track was estimated from (its ground truth).")
@click.option("--gt", "gt_file", type=click.Path(dir_okay=False, path_type=Path),
              help="YAML/JSON with the true final pose (translation_m, quaternion_xyzw), e.g. the nominal "
                   "inserted pose.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Report folder (default: TRACK_DIR/eval).")
@click.option("--bop-name", metavar="METHOD_DATASET-SPLIT",
              help="Name the BOP CSV as bop_toolkit's scripts expect, e.g. mvtop_mydataset-test "
                   "(default: estimates_bop.csv).")
@CONFIG_OPTION
def eval_cmd(track_dir: Path, log_path: Path | None, gt_file: Path | None, out_dir: Path | None, bop_name: str | None,
             config_path: Path | None) -> None:
    """Compare the pose track in TRACK_DIR (an `estimate` output) with the ground truth and
    write report.json, report.md, report.html (plots) and a BOP-format CSV.

    Metrics per frame and at the final frame: translation and rotation error, the paper's
    bounding-box pose error, ADD, ADD-S (BOP adi), MSSD, MSPD per camera, symmetry-aware errors, whether the final error
    is within the part's clearance (insertable), and NEES of the reported covariance.
    """
    from .pipelines.evaluate import evaluate

    cfg = None
    if config_path is not None:
        from .config import load_config

        cfg = load_config(config_path)
    out = out_dir if out_dir is not None else track_dir / "eval"
    report = evaluate(track_dir, log_path, gt_file, out, cfg, bop_name=bop_name)
    f = report["final"]
    click.echo(
        f"wrote {out}: final error {f['translation_error_mm']:.3f} mm, {f['rotation_error_deg']:.2f} deg; "
        + (f"insertion error {f['insertion_error_mm']:.3f} mm, insertable n/a (no object.clearance_m in the config); "
           if f["clearance_mm"] is None else
           f"insertion error {f['insertion_error_mm']:.3f} mm against {f['clearance_mm']:.3f} mm clearance: "
           f"{'insertable' if f['insertable'] else 'NOT insertable'}; ")
        + f"NEES {f['nees']:.1f} "
        f"({'within' if f['nees_within_bound'] else 'above'} the 95% bound {f['nees_bound']:.1f})"
    )


def parse_frames(spec: str) -> list[int]:
    """Frame indices from a ``--frames`` list such as ``0,5,10-20`` (ranges inclusive)."""
    frames: list[int] = []
    try:
        for part in spec.split(","):
            a, _, b = part.partition("-")
            frames += list(range(int(a), int(b) + 1)) if b else [int(a)]
    except ValueError:
        raise MvtopError(f"--frames: expected indices such as 0,5,10-20, got {spec!r}") from None
    return frames


@cli.command("render-masks")
@click.argument("log", type=LOG_PATH)
@CONFIG_OPTION
@click.option("--track", "track_dir", type=click.Path(file_okay=False, path_type=Path),
              help="An `estimate` output folder: render at its estimates.")
@click.option("--frames", "frames_spec", metavar="LIST", help="Frame indices, e.g. 0,5,10-20 (default: all).")
@click.option("--pose-ee", metavar="X,Y,Z,QX,QY,QZ,QW",
              help="Render at this object pose in the ee frame (metres, quaternion xyzw) instead of a track.")
@click.option("--no-video", is_flag=True, help="Skip masks.mp4.")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output folder.")
def render_masks_cmd(log: Path, config_path: Path | None, track_dir: Path | None, frames_spec: str | None,
                     pose_ee: str | None, no_video: bool, out_dir: Path) -> None:
    """Show what the estimator sees: per frame and sensor the image, the observed mask, the
    CAD mask rendered at the estimate (--track) and at the ground truth, an overlay with the
    IoU (observed blue, rendered yellow, truth outlined green), a contact sheet per frame and
    a video. Without --track it renders at the ground truth, or at --pose-ee: the quickest way
    to see a wrong extrinsic or grasp pose in a config."""
    import numpy as np

    from .config import load_config
    from .geometry import se3
    from .pipelines.render_masks import RenderMasksOptions, render_masks

    if config_path is None:
        raise MvtopError("render-masks needs --config CFG")
    if track_dir is not None and pose_ee is not None:
        raise MvtopError("give either --track or --pose-ee, not both")
    cfg = load_config(config_path)
    frames = parse_frames(frames_spec) if frames_spec else None
    T = None
    if pose_ee is not None:
        try:
            v = [float(x) for x in pose_ee.split(",")]
        except ValueError:
            v = []
        if len(v) != 7 or abs(np.linalg.norm(v[3:]) - 1.0) >= 1e-3:
            raise MvtopError(f"--pose-ee: expected x,y,z,qx,qy,qz,qw with a unit quaternion, got {pose_ee!r}")
        T = se3.from_quat_xyzw(np.array(v[3:]), np.array(v[:3]))
    options = RenderMasksOptions(frames=tuple(frames) if frames else None, pose_ee=T, video=not no_video)
    with _progress("render-masks") as update:
        summary = render_masks(log, cfg, out_dir, track_dir, options, progress=update)
    click.echo(f"wrote {out_dir}: {len(summary['frames'])} frames" + (", masks.mp4" if not no_video else ""))
    for fr in summary["frames"]:
        parts = []
        for name, rec in fr["sensors"].items():
            val = rec["iou_estimate"] if rec["iou_estimate"] is not None else rec["iou_truth"]
            parts.append(f"{name} {'n/a' if val is None else f'{val:.3f}'}")
        click.echo(f"frame {fr['frame']:4d}  IoU  " + "  ".join(parts))


@cli.group("benchmark")
def benchmark_group() -> None:
    """Measure speed, accuracy and long-log memory on this machine."""


@benchmark_group.command("speed")
@CONFIG_OPTION
@click.option("--particles", "particles_list", default="250,1000,4000", show_default=True, metavar="LIST",
              help="Comma-separated particle counts.")
@click.option("--repeats", type=click.IntRange(1, 100), default=7, show_default=True, help="Best of this many runs.")
@click.option("--no-reference", is_flag=True, help="Skip the one-pyrender-call-per-particle reference path.")
@click.option("--log", "log_path", type=LOG_PATH,
              help="Instead, run `estimate` with --config over this log and print the time per stage and frame "
                   "(first frame and later frames apart), the wall-over-log-time ratio and the masking backends' "
                   "time per frame.")
@click.option("--max-frames", type=click.IntRange(min=2), help="With --log: only the first frames.")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="With --log: change one setting of --config for the run, e.g. --set search.rival_every=0 (a "
                   "dotted config key, a YAML value; repeatable).")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as JSON for scripts.")
def benchmark_speed_cmd(config_path: Path | None, particles_list: str, repeats: int, no_reference: bool,
                        log_path: Path | None, max_frames: int | None, settings: tuple[str, ...],
                        as_json: bool) -> None:
    """Particle x sensor evaluations per second (render + IoU in a region of interest) of the
    batched renderer, beside one pyrender call per particle, for 2 cameras and 2 tactile sensors
    looking at the object of --config (default: the simulator's cube). With --log, the estimate's
    time per stage and frame on that log instead."""
    import json
    import os

    if log_path is not None:
        if config_path is None:
            raise MvtopError("--log needs --config (the estimate runs with it)")
        _profile_estimate(log_path, config_path, max_frames, settings, as_json)
        return
    if settings:
        raise MvtopError("--set needs --log (it changes the config of the estimate that --log times)")

    from .benchmarks.render_speed import benchmark_render

    try:
        counts = [int(v) for v in particles_list.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise MvtopError(f"--particles: expected a comma-separated list of positive integers, got {particles_list!r}")
    meshes = None
    if config_path is not None:
        from .config import load_config
        from .io.meshes import load_mesh

        cfg = load_config(config_path)
        meshes = {cfg.object.name: load_mesh(cfg.object.mesh, cfg.object.units, "object mesh")}
    else:
        from .sim.objects import get_object

        meshes = {"cube": get_object("cube").mesh}
    rows = benchmark_render(counts, meshes=meshes, reference=not no_reference, repeats=repeats)
    out = [{"particles": r["particles"], "evals_per_s": round(r["evals_per_s"], 1),
            "reference_evals_per_s": (None if r["reference_evals_per_s"] is None
                                      else round(r["reference_evals_per_s"], 1)),
            "mesh": r["mesh"], "threads": r["threads"]} for r in rows]
    if as_json:
        click.echo(json.dumps(out))
        return
    click.echo(f"machine: {os.cpu_count()} cores; numba threads: {out[0]['threads']}; 2 cameras + 2 tactile sensors")
    click.echo(f"{'mesh':<10} {'particles':>9} {'evals/s':>10} {'pyrender evals/s':>17} {'speed-up':>9}")
    for r in out:
        ref = r["reference_evals_per_s"]
        ratio = f"{r['evals_per_s'] / ref:8.0f}x" if ref else "        -"
        click.echo(f"{r['mesh']:<10} {r['particles']:>9} {r['evals_per_s']:>10.0f} "
                   f"{ref or float('nan'):>17.0f} {ratio}")


def _profile_estimate(log_path: Path, config_path: Path, max_frames: int | None, settings: tuple[str, ...],
                      as_json: bool) -> None:
    """``benchmark speed --log``: the estimate's time per stage, and the masking backends'."""
    import json
    import os

    from .benchmarks.frame_profile import profile_estimate
    from .benchmarks.masking_speed import masking_speed
    from .config import load_config, parse_settings

    cfg = load_config(config_path, parse_settings(settings))
    with _progress(f"profile {log_path.name}") as update:
        update(0, 2)
        prof = profile_estimate(log_path, cfg, max_frames)
        update(1, 2)
        masking = masking_speed(log_path, cfg)
        update(2, 2)
    if as_json:
        click.echo(json.dumps({**prof, "masking_ms_per_frame": masking}))
        return
    click.echo(f"machine: {os.cpu_count()} cores; {log_path}: {prof['frames_processed']} frames over "
               f"{prof['log_s']:.2f} s of log, {cfg.filter.num_particles} particles, modalities "
               f"{','.join(cfg.modalities)}; run {prof['run_time_s']:.1f} s, start-up {prof['startup_s']:.2f} s")
    first, later = prof["first_frame"], prof.get("later_frames_mean") or {}
    click.echo(f"{'stage [ms per frame]':<28} {'first frame':>12} {'later (mean)':>13}")
    names = (("read_s", "read and decode"), ("masking_s", "masking (observation)"),
             ("search_s", "search and re-search"), ("filter_s", "prediction + refinement"),
             ("checks_s", "mode and rival checks"), ("diagnostics_s", "diagnostics"),
             ("likelihood_s", "  likelihood, in all of these"),
             ("step_s", "whole step"))
    for key, label in names:
        click.echo(f"{label:<28} {1e3 * first[key]:>12.1f} {1e3 * later.get(key, float('nan')):>13.1f}")
    for key, label in (("likelihood_calls", "likelihood calls"), ("poses_scored", "poses scored")):
        click.echo(f"{label:<28} {first[key]:>12.0f} {later.get(key, float('nan')):>13.0f}")
    click.echo(f"later frames in tracking mode: {prof.get('tracked_frames', 0)} of {max(prof['frames'] - 1, 0)}")
    ratio = prof["wall_over_log"]
    click.echo("wall time over log time (frames after the first): " + ("n/a" if ratio is None else f"{ratio:.2f}"))
    click.echo(f"masking backends per frame ({cfg.masking.camera.backend} cameras, "
               f"{cfg.masking.tactile.backend}/depth tactile): "
               + ", ".join(f"{k[:-3].replace('_', ' ')} {v:.1f} ms" for k, v in masking.items()))


def benchmark_scene_option():
    """``--scene default|hard``: the simulated camera scene of a benchmark's runs."""
    return click.option("--scene", type=click.Choice(["default", "hard"]), default="default", show_default=True,
                        help="Simulated camera scene: hard adds shadows and dark faces, glossy plastic, a cluttered "
                             "textured background and lighting that changes between frames (mvtop simulate --scene "
                             "hard). One scene per --out folder.")


def benchmark_masks_option():
    """``--recorded-masks-px N``: a simulated segmenter's camera masks recorded with the images."""
    return click.option("--recorded-masks-px", "recorded_masks_px", type=click.IntRange(0, 20), default=None,
                        help="Simulate a segmenter node on the robot (the paper's supervised setting): each camera "
                             "image's object mask is recorded with it, its outline off by up to this many pixels (0: "
                             "exact), and the estimator reads it (masking backend topic). One setting per --out "
                             "folder. Default: masks made from the images.")


def benchmark_settings_option():
    """``--set KEY=VALUE`` (repeatable): config settings over every scene config of a benchmark."""
    return click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
                        help="Change one config setting in every run, e.g. --set contact.softness_m=1.0e-04 "
                             "(a dotted config key, a YAML value; repeatable). Recorded with each run; one set of "
                             "settings per --out folder.")


def benchmark_grasp_options(command):
    """The options every simulated benchmark shares: ``--out``, which objects (``--objects``,
    ``--object-file``) and which grasps (``--poses`` from ``--first-seed``)."""
    options = [
        click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
                     help="Benchmark folder (runs are kept there; running again resumes)."),
        click.option("--objects", default=None, metavar="LIST", help="Comma-separated objects (default: all five; "
                     "none with --object-file unless given)."),
        click.option("--object-file", "object_files", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
                     help="Also benchmark your own part, described by this object file (repeat for several)."),
        click.option("--poses", type=click.IntRange(1, 10000), default=100, show_default=True,
                     help="Grasps per object."),
        click.option("--first-seed", type=click.IntRange(0, 2**31 - 1), default=1000, show_default=True,
                     help="Seed of the first grasp; grasp i uses seed FIRST_SEED + i (another range: grasps the "
                          "default tables never used)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def benchmark_ray_option():
    """``--ray ADDRESS``: a benchmark's runs as Ray tasks (``batch/engine.py``)."""
    return click.option("--ray", "ray_address", metavar="ADDRESS",
                        help="Run the runs as Ray tasks: local, auto or a cluster address (as for estimate); every "
                             "worker writes into --out, which must be on a file system they share.")


def _benchmark_methods(methods: str, known: tuple[str, ...]) -> tuple[str, ...]:
    """The comma-separated ``--methods``; an unknown one is an error naming those ``known``."""
    meths = tuple(m.strip() for m in methods.split(","))
    bad = [m for m in meths if m not in known]
    if bad:
        raise MvtopError(f"--methods: unknown {', '.join(bad)} (expected {', '.join(known)})")
    return meths


def _benchmark_objects(objects: str | None, object_files: tuple[Path, ...]) -> tuple[tuple[str, ...], tuple]:
    """A benchmark's objects: those of ``--objects`` (default: every built-in object, none when
    object files are given) and then those of the ``--object-file`` files; and (name, resolved
    path) of each object file. An unknown object or a name used twice is an error."""
    from .sim.object_file import load_object_file
    from .sim.objects import get_object, list_objects

    objs = tuple(o.strip() for o in objects.split(",")) if objects else () if object_files else tuple(list_objects())
    for o in objs:
        get_object(o)
    files = tuple((load_object_file(f).name, str(f.resolve())) for f in object_files)
    clash = sorted({n for n, _ in files if n in objs or [m for m, _ in files].count(n) > 1})
    if clash:
        raise MvtopError(f"--object-file: object name {clash[0]!r} is used twice (object names name the runs)")
    return objs + tuple(n for n, _ in files), files


@benchmark_group.command("accuracy")
@benchmark_grasp_options
@click.option("--methods", default="M-VTOP,M-VOP,M-TOP", show_default=True, metavar="LIST",
              help="M-VTOP (vision+touch+contact), M-VOP (vision), M-TOP (touch+contact), CHSEL (baseline: "
                   "point-set registration of the same observations; needs pip install -e '.[baseline]').")
@click.option("--frames", type=click.IntRange(4, 1000), default=30, show_default=True, help="Frames per episode.")
@benchmark_scene_option()
@benchmark_masks_option()
@benchmark_settings_option()
@particles_option()
@click.option("--workers", type=click.IntRange(1, 64), default=1, show_default=True, help="Parallel processes.")
@click.option("--import-results", "import_results", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="results.jsonl.gz of another benchmark folder: its runs count as done here (continue a "
                   "benchmark on another machine).")
@click.option("--summary-only", is_flag=True, help="Only write and print the tables over the runs already "
              "finished (or imported); make no new run.")
@benchmark_ray_option()
def benchmark_accuracy_cmd(out_dir: Path, objects: str | None, object_files: tuple[Path, ...], poses: int,
                           first_seed: int, methods: str, frames: int, scene: str, recorded_masks_px: int | None,
                           settings: tuple[str, ...], particles: int | None, workers: int,
                           import_results: Path | None, summary_only: bool, ray_address: str | None) -> None:
    """Reproduce the paper's simulated experiments: every object x grasp x method is simulated,
    estimated and evaluated; prints median / p95 final errors (figure 4), insertion success
    rates (table I) and run times, and writes them to OUT/summary.md and summary.json, with
    log-scale box plots of the errors per object and method in OUT/summary.html. OUT/results.jsonl.gz
    keeps every finished run in compact form, for --import-results elsewhere."""
    from .benchmarks.accuracy import METHODS, AccuracyOptions, format_table, run_accuracy
    from .config import parse_settings

    objs, files = _benchmark_objects(objects, object_files)
    meths = _benchmark_methods(methods, METHODS)
    options = AccuracyOptions(objects=objs, poses=poses, first_seed=first_seed, methods=meths, frames=frames,
                              particles=particles, workers=workers,
                              import_results=import_results, summary_only=summary_only, object_files=files,
                              ray=ray_address, scene=scene, recorded_masks_px=recorded_masks_px,
                              settings=parse_settings(settings))
    with _stops_resumably("benchmark accuracy", out_dir, "runs"), _progress("benchmark accuracy") as update:
        summary = run_accuracy(out_dir, options, progress=update)
    click.echo(format_table(summary))
    click.echo(f"wrote {out_dir}/summary.md and summary.html ({summary['seconds_this_run']:.0f} s in this run)")


@benchmark_group.command("insertion")
@benchmark_grasp_options
@click.option("--methods", default="M-VTOP,M-VOP,M-TOP", show_default=True, metavar="LIST",
              help="M-VTOP (vision+touch+contact), M-VOP (vision), M-TOP (touch+contact).")
@click.option("--attempts", type=click.IntRange(1, 20), default=3, show_default=True,
              help="Descents per grasp: after a stalled one the robot backs off, re-aligns and retries.")
@benchmark_scene_option()
@benchmark_masks_option()
@benchmark_settings_option()
@particles_option()
@click.option("--workers", type=click.IntRange(1, 64), default=1, show_default=True, help="Parallel processes.")
@click.option("--keep-logs", is_flag=True, help="Write every attempt as an MCAP log (OUT/runs/RUN/logs/).")
@click.option("--import-results", "import_results", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="results.jsonl.gz of another insertion benchmark folder: its runs count as done here.")
@click.option("--summary-only", is_flag=True, help="Only write and print the tables over the runs already "
              "finished; make no new run.")
@benchmark_ray_option()
def benchmark_insertion_cmd(out_dir: Path, objects: str | None, object_files: tuple[Path, ...], poses: int,
                            first_seed: int, methods: str, attempts: int, scene: str, recorded_masks_px: int | None,
                            settings: tuple[str, ...], particles: int | None, workers: int, keep_logs: bool,
                            import_results: Path | None, summary_only: bool, ray_address: str | None) -> None:
    """The paper's Table I in closed loop: every object x grasp x method is inserted in the
    simulator, the robot aligning the estimated object pose with the receptacle and retrying
    after a stalled descent; prints the success rates (per object and method, and their
    average), attempts and time to insert, and writes them to OUT/summary.md and summary.json;
    OUT/results.jsonl.gz keeps every finished run."""
    from .benchmarks.insertion import METHODS, InsertionBenchmarkOptions, format_table, run_insertion_benchmark
    from .config import parse_settings

    objs, files = _benchmark_objects(objects, object_files)
    meths = _benchmark_methods(methods, METHODS)
    options = InsertionBenchmarkOptions(objects=objs, poses=poses, first_seed=first_seed, methods=meths,
                                        attempts=attempts,
                                        particles=particles, workers=workers, object_files=files,
                                        keep_logs=keep_logs, import_results=import_results,
                                        summary_only=summary_only, ray=ray_address, scene=scene,
                                        recorded_masks_px=recorded_masks_px, settings=parse_settings(settings))
    with _stops_resumably("benchmark insertion", out_dir, "runs"), _progress("benchmark insertion") as update:
        summary = run_insertion_benchmark(out_dir, options, progress=update)
    click.echo(format_table(summary))
    click.echo(f"wrote {out_dir}/summary.md ({summary['seconds_this_run']:.0f} s in this run)")


@benchmark_group.command("long-log")
@click.option("--size-gb", type=click.FloatRange(0.01, 100), default=2.0, show_default=True,
              help="Size of the simulated log [GB, 1e9 bytes].")
@particles_option(200)
@click.option("--object", "object_name", default="cube", show_default=True, metavar="NAME", help="Object to simulate.")
@seed_option(0, "Simulation seed")
@click.option("--keep", type=click.Path(file_okay=False, path_type=Path),
              help="Keep the log, config and track in this folder (a log made there before with the same "
                   "object, seed and size is reused); default: a temporary folder, deleted afterwards.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures (and the RSS samples) as JSON.")
def benchmark_long_log_cmd(size_gb: float, particles: int, object_name: str, seed: int, keep: Path | None,
                           as_json: bool) -> None:
    """Memory and time of `mvtop estimate` on a long log: simulates one long insertion episode with
    uncompressed images (about 2.9 MB per frame: the default 2 GB is about 690 frames; it takes
    minutes to simulate), runs the estimate on it in a child process and prints the log size,
    frames, peak resident memory, seconds per frame over the first and last quarter of the frames
    (linear time: equal) and the total time."""
    import json

    from .benchmarks.long_log import LongLogOptions, benchmark_long_log
    from .sim.objects import get_object

    get_object(object_name)
    options = LongLogOptions(size_gb=size_gb, particles=particles, object_name=object_name, seed=seed, keep=keep)
    bars = contextlib.ExitStack()
    updates: dict = {}

    def update(stage: str, done: int, total: int) -> None:
        if stage not in updates:  # one bar per stage, the previous one closed
            bars.close()
            updates[stage] = bars.enter_context(_progress(f"{stage} long log"))
        updates[stage](done, total)

    with bars:
        result = benchmark_long_log(options, update)
    log, est = result["log"], result["estimate"]
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(f"log: {log['bytes'] / 1e9:.2f} GB, {log['frames']} frames at 10 Hz "
               f"({log['contact_frames']} in contact): "
               f"simulated {object_name} episode (seed {seed}), per frame 2 raw rgb8 camera images 640x480, 2 raw "
               f"rgb8 tactile images and 2 32FC1 depth maps, uncompressed chunks"
               + (f"; reused from {result['folder']}" if log.get("reused") else ""))
    click.echo(f"estimate: {est['frames']} frames, {particles} particles, {est['run_time_s']:.0f} s "
               f"({est['run_time_s'] / est['frames']:.3f} s per frame; {est['wall_s']:.0f} s with process start)")
    fq, lq = est["rss_first_quarter_mb"], est["rss_last_quarter_mb"]
    click.echo(f"peak RSS: {est['peak_rss_mb']:.0f} MB (getrusage of the child); median RSS over the first / last "
               f"quarter of the frames: {fq or float('nan'):.0f} / {lq or float('nan'):.0f} MB")
    def pair(first: str, last: str) -> str:
        a, b = est[first], est[last]
        if a is None or b is None:
            return "n/a"
        return f"{a:.3f} / {b:.3f} (ratio {b / a:.2f})"

    click.echo("seconds per frame, first / last quarter of the frames: wall "
               f"{pair('s_per_frame_first_quarter', 's_per_frame_last_quarter')}"
               f", CPU {pair('cpu_s_per_frame_first_quarter', 'cpu_s_per_frame_last_quarter')}")
    click.echo(f"seconds per frame, first / last half of the contact phase (frames {est['contact_from_frame']}-"
               f"{est['frames'] - 1}): wall {pair('s_per_frame_contact_first_half', 's_per_frame_contact_last_half')}, "
               f"CPU {pair('cpu_s_per_frame_contact_first_half', 'cpu_s_per_frame_contact_last_half')}")
    click.echo(f"checkpoint: {est['checkpoint_ms_per_frame']} ms per frame")
    if result["folder"]:
        click.echo(f"kept in {result['folder']}")


def main(argv: list[str] | None = None) -> None:
    """Console entry point: runs the CLI and turns MvtopError into one line and exit code 2."""
    try:
        cli.main(args=argv, prog_name="mvtop", standalone_mode=False)
    except MvtopError as err:
        click.echo(f"mvtop: error: {err}", err=True)
        sys.exit(err.exit_code)
    except click.exceptions.Abort:
        click.echo("mvtop: interrupted", err=True)
        sys.exit(130)
    except click.ClickException as err:
        err.show()
        sys.exit(err.exit_code)
    except KeyboardInterrupt:
        click.echo("mvtop: interrupted", err=True)
        sys.exit(130)
    except BrokenPipeError:
        sys.exit(0)
