"""One closed-loop insertion with the simulated sensors and the online estimator.

``sim.closed_loop`` moves the robot; this module gives it eyes: each frame is rendered as
``mvtop simulate`` renders it (``simulate.SensorRig``: two cameras, two GelSight-like tactile
sensors, their noise and compression) and handed to ``Estimator.step`` as the ``records.Frame``
that reading the log back would give (the images encoded as the log stores them and decoded
again, the tactile depth, the sensor and end-effector poses, the contact flag, and with
``SimulateOptions.mask_topics`` each camera's recorded object mask as a segmenter node would
publish it; no ground truth). The frames are made one at a time, since where the robot moves
next depends on the estimate. With ``log_dir`` every attempt is also written as an MCAP log
(``attempt_<n>.mcap``, with ground truth) that ``mvtop estimate`` and ``mvtop eval`` read with
the scene's config.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..config import Config
from ..estimator import Estimator
from ..io.images import decode_compressed, decode_mask, encode_compressed, encode_mask_png, encode_raw
from ..io.mcap_writer import LogWriter
from ..records import Frame, SensorImage
from ..sim import gripper as grip
from ..sim.closed_loop import ControllerOptions, InsertionResult, PoseEstimator, run_insertion
from ..sim.episode import Collider, EpisodeState
from ..sim.object_file import resolve_object
from ..sim.scene import board_mesh, receptacle_pose
from .simulate import TACTILE_SIDES, SensorRig, SimulateOptions, write_images, write_robot

_TOPIC = re.compile(r"^/(cameras|tactile)/([^/]+)/")


@dataclass(frozen=True)
class InsertionOptions:
    """A closed-loop insertion: the sensors (``SimulateOptions``: image size, noise, formats, the
    camera scene of ``simulate.scene_options``; its ``episode`` gives the grasp offset, slip and
    frame rate) and the controller."""

    sensors: SimulateOptions = field(default_factory=SimulateOptions)
    controller: ControllerOptions = field(default_factory=ControllerOptions)


def filter_estimator(cfg: Config, states: dict[int, EpisodeState]) -> PoseEstimator:
    """The M-VTOP filter (``Estimator.from_config(cfg)``) as the controller's estimator: it sees
    the frame only, and of it the sensors of the config's modalities. ``states`` maps a stamp
    to the robot's state then (filled by the sensors), from which the finger frames' TF is
    answered, as a log's TF would."""

    def frame_pose(tf_frame: str, stamp_ns: int) -> np.ndarray:
        side = tf_frame.removeprefix("finger_")
        st = states[stamp_ns]
        if side not in TACTILE_SIDES:
            raise ValueError(f"no TF frame {tf_frame!r} in the simulated insertion")
        return st.T_world_ee @ grip.finger_poses(st.finger_opening_m)[side]

    estimator = Estimator.from_config(cfg, frame_pose)
    # the sensors of the method's modalities, as ``mvtop estimate`` reads them (``sensor_topics``)
    cameras = {c.name for c in cfg.sensors.cameras} if "vision" in cfg.modalities else set()
    tactile = {t.name for t in cfg.sensors.tactile} if "tactile" in cfg.modalities else set()

    def estimate(frame: Frame, truth: EpisodeState) -> np.ndarray:
        frame = replace(frame, cameras={k: v for k, v in frame.cameras.items() if k in cameras},
                        tactile={k: v for k, v in frame.tactile.items() if k in tactile})
        return estimator.step(frame).T_ee_object

    return estimate


class _FrameRecorder:
    """Takes what ``simulate.write_images`` writes: passes it on to ``log`` (if any) and keeps
    each image as the log reader would give it back (``SensorImage``)."""

    def __init__(self, log: LogWriter | None, rig: SensorRig, T_world_ee: np.ndarray, opening_m: float):
        self.log = log
        self.rig = rig
        self.T_world_ee = T_world_ee
        self.opening_m = opening_m
        self.images: dict[str, dict] = {}

    def _slot(self, topic: str) -> dict:
        m = _TOPIC.match(topic)
        if m is None:  # pragma: no cover - write_images writes only camera and tactile topics
            raise ValueError(f"unexpected topic {topic!r}")
        return self.images.setdefault(m.group(2), {"kind": m.group(1)})

    def write_compressed_image(self, topic, rgb, stamp_ns, frame_id, *, fmt, jpeg_quality):
        if self.log is not None:
            self.log.write_compressed_image(topic, rgb, stamp_ns, frame_id, fmt=fmt, jpeg_quality=jpeg_quality)
        msg = SimpleNamespace(**encode_compressed(rgb, fmt, jpeg_quality))
        self._slot(topic).update(image=decode_compressed(msg, topic), stamp_ns=stamp_ns)

    def write_image(self, topic, image, stamp_ns, frame_id, *, encoding):
        if self.log is not None:
            self.log.write_image(topic, image, stamp_ns, frame_id, encoding=encoding)
        self._slot(topic).update(image=np.ascontiguousarray(image), stamp_ns=stamp_ns)

    def write_depth(self, topic, depth_m, stamp_ns, frame_id):
        if self.log is not None:
            self.log.write_depth(topic, depth_m, stamp_ns, frame_id)
        self._slot(topic)["depth"] = np.asarray(depth_m, dtype=np.float32)

    def write_mask(self, topic, labels, stamp_ns, frame_id, *, fmt):
        if self.log is not None:
            self.log.write_mask(topic, labels, stamp_ns, frame_id, fmt=fmt)
        labels = np.asarray(labels)
        fields = (encode_mask_png(labels) if fmt == "png"
                  else encode_raw(labels, "mono8" if labels.dtype == np.uint8 else "mono16"))
        self._slot(topic)["mask"] = decode_mask(SimpleNamespace(**fields), topic)

    def write_camera_info(self, topic, camera, stamp_ns, frame_id):
        if self.log is not None:
            self.log.write_camera_info(topic, camera, stamp_ns, frame_id)
        self._slot(topic)["camera"] = camera

    def sensor_images(self) -> tuple[dict[str, SensorImage], dict[str, SensorImage]]:
        cams = {c.name: c.T_world_camera for c in self.rig.cameras}
        fingers = grip.finger_poses(self.opening_m)
        cameras, tactile = {}, {}
        for name, s in self.images.items():
            if s["kind"] == "cameras":
                T = cams[name]
            else:
                T = self.T_world_ee @ fingers[name] @ self.rig.T_finger_tac
            img = SensorImage(name, s["stamp_ns"], s["image"], s["camera"], T, s.get("depth"), self.T_world_ee,
                              s.get("mask"))
            (cameras if s["kind"] == "cameras" else tactile)[name] = img
        return cameras, tactile


class _Sensors:
    """The ``Observe`` of ``run_insertion``: renders each state's frame with the rig, writes
    it to the current attempt's log when ``log_dir`` is given."""

    def __init__(self, rig: SensorRig, options: SimulateOptions, cam_rng, tac_rng, light_rng, mask_rng,
                 states: dict[int, EpisodeState], log_dir: Path | None):
        self.rig, self.options, self.cam_rng, self.tac_rng, self.light_rng = rig, options, cam_rng, tac_rng, light_rng
        self.mask_rng = mask_rng
        self.states = states
        self.log_dir = log_dir
        self.log: LogWriter | None = None
        self.attempt = 0
        self.logs: list[Path] = []

    def __call__(self, state: EpisodeState, index: int, attempt: int) -> Frame:
        self.states[state.stamp_ns] = state
        if self.log_dir is not None and attempt != self.attempt:
            self.close()
            path = self.log_dir / f"attempt_{attempt}.mcap"
            self.log = LogWriter(path, compression=self.options.compression)
            self.log.write_tf(self.rig.static_transforms(self.options.kinematics), state.stamp_ns, static=True)
            self.logs.append(path)
        self.attempt = attempt
        if self.log is not None:
            write_robot(self.log, state, self.options.kinematics)
        rec = _FrameRecorder(self.log, self.rig, state.T_world_ee, state.finger_opening_m)
        capture = {name: state.stamp_ns for name in ("front", "side", *TACTILE_SIDES)}
        write_images(rec, state, capture, [state], self.rig, self.options, self.cam_rng, self.tac_rng,
                     self.mask_rng, self.light_rng)
        cameras, tactile = rec.sensor_images()
        return Frame(index=index, stamp_ns=state.stamp_ns, T_world_ee=state.T_world_ee, cameras=cameras,
                     tactile=tactile, contact=bool(state.contact), finger_opening_m=state.finger_opening_m)

    def close(self) -> None:
        if self.log is not None:
            self.log.close()
            self.log = None


def insert(object_name: str, seed: int, cfg: Config | None, options: InsertionOptions = InsertionOptions(),
           log_dir: Path | None = None, estimator: PoseEstimator | None = None) -> InsertionResult:
    """One grasp of ``object_name`` (a built-in object or an object file) with ``seed`` in closed
    loop. The estimator is the M-VTOP filter of ``cfg`` (its modalities decide M-VTOP, M-VOP or
    M-TOP) unless ``estimator`` is given. The same seed gives the same grasp, start pose,
    images and slip whatever the method (the estimate decides the motion, and so what follows).
    ``log_dir``: write each attempt as ``attempt_<n>.mcap`` there."""
    if cfg is None and estimator is None:
        raise ValueError("give a config or an estimator")
    spec = resolve_object(object_name)
    sim = options.sensors
    if sim.timing.jitter_s or sim.timing.drop_fraction or sim.timing.camera_every != 1:
        raise ValueError("closed-loop insertion renders every sensor at every frame (default SensorTiming)")
    rng = np.random.default_rng(seed)
    ep_rng, cam_rng, tac_rng, scene_rng = (np.random.default_rng(s) for s in rng.integers(0, 2**63, size=4))
    # drawn as ``simulate`` draws them (its timing generator unused here): a hard scene
    # (``simulate.scene_options``) has the clutter of ``mvtop simulate``'s with the same seed, and
    # recorded masks (``SimulateOptions.mask_topics``) are degraded by the same generator
    rng.integers(0, 2**63)
    mask_rng, light_rng, clutter_rng = (np.random.default_rng(s) for s in rng.integers(0, 2**63, size=3))
    T_world_rec = receptacle_pose(spec.receptacle_mesh)
    collider = Collider(spec.mesh, [(spec.receptacle_mesh, T_world_rec), (board_mesh(), np.eye(4))])
    states: dict[int, EpisodeState] = {}
    if log_dir is not None:
        Path(log_dir).mkdir(parents=True, exist_ok=True)
    rig = SensorRig.build(spec, T_world_rec, sim, scene_rng, tac_rng, clutter_rng)
    sensors = _Sensors(rig, sim, cam_rng, tac_rng, light_rng, mask_rng, states,
                       None if log_dir is None else Path(log_dir))
    try:
        est = estimator if estimator is not None else filter_estimator(cfg, states)
        return run_insertion(T_world_rec, spec.insertion_depth_m, spec.grasp, spec.mesh, collider, sim.episode,
                             options.controller, ep_rng, est, sensors, spec.grasp_squeeze)
    finally:
        sensors.close()
        rig.close()


def method_config(cfg: Config, modalities: tuple[str, ...], particles: int | None, seed: int) -> Config:
    """``cfg`` with the method's modalities, the particle count (None: the config's) and the
    filter seed."""
    f = cfg.filter if particles is None else replace(cfg.filter, num_particles=particles)
    return replace(cfg, modalities=tuple(modalities), filter=replace(f, seed=seed))
