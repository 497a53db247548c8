"""A log's observations as labelled point sets in the end-effector frame (see ``points``).

The same observations M-VTOP uses, turned into points: tactile indentation depth (or, without
a depth topic, the tactile contact mask, placed on the undeformed gel plane), camera object
masks chosen by Algorithm 1-2 among the classical proposals and a GrabCut seeded by the grasp
prior (the estimator's first-frame masks: the baseline has no belief of its own to prompt
with), the end effector's pose from TF and the fixed environment's meshes. The contact signal
has no point-set form and is not used.

The object is held in the gripper, so points of every frame are expressed in the end
effector's frame ``ee`` at that frame's time and pooled: a rigid grasp makes them consistent;
slip under contact makes early frames disagree with later ones (``last_frames`` bounds the
pool).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...config import Config
from ...errors import EstimationError
from ...estimator.observation import ObservationModel
from ...estimator.prior import GraspPriorModel
from ...estimator.scene import SceneModel
from ...geometry import se3
from ...io.frames import FrameReader
from ...io.mcap_reader import McapLog
from ...pipelines.estimate import log_topics, sensor_topics
from ...records import Frame
from .points import LabelledPoints, camera_free_points, environment_free_points, tactile_points

_REGION_MARGIN_M = 1e-3  # added to the radius of the region the object can occupy


@dataclass(frozen=True)
class PointOptions:
    """How observations become points.

    stride_px : every stride-th pixel (in image pixels) of tactile images and camera ROIs
    ray_spacing_m : free-space samples along camera rays [m]
    env_spacing_m : lattice spacing of the free points inside the environment [m]
    mask_margin_px : camera object masks are grown by this many image pixels before carving: the
        masks chosen without a belief miss up to ~4 px of thin parts (conn1: carving then cut
        1-2 mm into the part at 1 px, about 1 mm at 3 px)
    voxel_m : each frame's points, then the pooled points, are thinned to one per label and
        voxel of this side [m]
    last_frames : pool the last this many frames (None: all)
    seed : seeds the grasp-prior candidates of the camera mask selection and GrabCut
    """

    stride_px: int = 2
    ray_spacing_m: float = 5e-4
    env_spacing_m: float = 1e-3
    mask_margin_px: int = 3
    voxel_m: float = 5e-4
    last_frames: int | None = None
    seed: int = 0


@dataclass(frozen=True)
class LogPoints:
    """Pooled points (ee frame) and the last pooled frame's index, stamp and ``T_world_ee``."""

    points: LabelledPoints
    frames_used: int
    last_index: int
    last_stamp_ns: int
    T_world_ee: np.ndarray
    T_world_object_gt: np.ndarray | None


def object_region(cfg: Config, scene: SceneModel) -> tuple[np.ndarray, float]:
    """Centre (3,) [m, ee frame] and radius [m] of a sphere holding the object at every pose
    of the grasp prior (its box, or 3 sigmas of a gaussian prior)."""
    g = cfg.grasp_prior
    T_nom = g.pose.matrix()
    V = np.asarray(scene.object_mesh.vertices, dtype=np.float64)
    centre_obj = 0.5 * (V.min(axis=0) + V.max(axis=0))
    r_obj = float(np.max(np.linalg.norm(V - centre_obj, axis=1)))
    k = 1.0 if g.distribution == "uniform" else 3.0
    # translation box diagonal; a rotation of theta about the object origin moves a point at
    # distance r from it by at most r * theta
    r_origin = float(np.max(np.linalg.norm(V, axis=1)))
    radius = r_obj + k * g.translation_m * np.sqrt(3) + r_origin * k * np.radians(g.rotation_deg) * np.sqrt(3)
    return se3.transform_points(T_nom, centre_obj[None])[0], radius + _REGION_MARGIN_M


def prior_samples(cfg: Config, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) ``T_ee_object`` drawn from the config's grasp prior."""
    return GraspPriorModel(cfg.grasp_prior, cfg.search.bound).sample(n, rng).poses


class FramePoints:
    """Turns frames into labelled points in the ee frame (no io: frames in, points out)."""

    def __init__(self, cfg: Config, scene: SceneModel, frame_pose, options: PointOptions = PointOptions()):
        self.cfg = cfg
        self.scene = scene
        self.frame_pose = frame_pose
        self.options = options
        self.observations = ObservationModel(cfg, scene, frame_pose)
        self.tactile_cfg = {t.name: t for t in cfg.sensors.tactile}
        self.centre_ee, self.radius = object_region(cfg, scene)
        self.candidates = prior_samples(cfg, cfg.masking.candidates, np.random.default_rng(options.seed))

    def __call__(self, frame: Frame) -> LabelledPoints:
        o = self.options
        T_ee_world = se3.invert(frame.T_world_ee)
        threshold = self.cfg.masking.tactile_depth_threshold_m
        parts = []
        for name, img in frame.tactile.items():
            gel = self.tactile_cfg[name].gel_distance_m
            if img.depth is not None:
                ind = np.asarray(img.depth, dtype=np.float64)
            else:  # a contact mask only: the object's surface is taken on the undeformed gel plane
                ind = np.where(self.observations.observer.tactile_mask(img), 2 * threshold, 0.0)
            pts = tactile_points(ind, img.camera, gel, contact_threshold_m=threshold, stride_px=o.stride_px)
            parts.append(pts.transformed(T_ee_world @ img.T_world_sensor))
        for name, img in frame.cameras.items():
            parts.append(self._camera_points(frame, name).transformed(T_ee_world @ img.T_world_sensor))
        if self.scene.sdf is not None:
            centre_world = se3.transform_points(frame.T_world_ee, self.centre_ee[None])[0]
            env = environment_free_points(self.scene.sdf.env_sdf.query, centre_world, self.radius,
                                          spacing_m=o.env_spacing_m)
            parts.append(env.transformed(T_ee_world))
        return LabelledPoints.concat(parts).downsampled(o.voxel_m)

    def _camera_points(self, frame: Frame, name: str) -> LabelledPoints:
        """Free points carved by one camera, in its optical frame."""
        img = frame.cameras[name]
        T_sensor_world = se3.invert(img.T_world_sensor)
        rois = self.observations.rois(frame, self.candidates, [name])
        occluders = {name: self.observations.occluders(img)}
        weights = np.full(len(self.candidates), 1.0 / len(self.candidates))
        mask = self.observations.camera_masks(frame, {name: img}, rois, occluders, self.candidates, weights,
                                              self.options.seed).get(name)
        if mask is None:  # no object seen: nothing can be carved safely
            return LabelledPoints.empty()
        mask = mask[0]
        roi, occluders = rois[name], occluders[name]
        depth = np.full(roi.shape, np.inf)
        for mesh_id, T_sensor_mesh in occluders:
            depth = np.minimum(depth, self.scene.renderer.render_depth(mesh_id, T_sensor_mesh, img.camera, roi)[0])
        centre = se3.transform_points(T_sensor_world @ frame.T_world_ee, self.centre_ee[None])[0]
        # ROI pixels are 1/scale image pixels wide: the stride and the mask margin are in image pixels
        k = 1.0 / roi.scale
        o = self.options
        return camera_free_points(
            mask, roi.camera(img.camera), centre, self.radius, occluder_depth_m=depth, spacing_m=o.ray_spacing_m,
            stride_px=max(1, round(o.stride_px / k)),
            mask_margin_px=max(1 if o.mask_margin_px else 0, round(o.mask_margin_px / k)),
        )


def log_points(
    log_path: Path, cfg: Config, options: PointOptions = PointOptions(), max_frames: int | None = None
) -> LogPoints:
    """Points of the frames of ``log_path`` (the last ``options.last_frames`` of the first
    ``max_frames``), pooled in the ee frame and thinned to ``options.voxel_m``."""
    scene = SceneModel(cfg, build_contact=True)
    sensors = sensor_topics(cfg)
    if not sensors:
        raise EstimationError("no sensor is enabled: check modalities and sensors in the config")
    per_frame: list[tuple[Frame, LabelledPoints]] = []
    with McapLog(log_path) as log:
        reader = FrameReader(log, sensors, log_topics(cfg))
        to_points = FramePoints(cfg, scene, lambda frame, t: reader.tf.lookup(cfg.frames.world, frame, t), options)
        frames = []
        for frame in reader:
            frames.append(frame)
            if max_frames is not None and len(frames) >= max_frames:
                break
        if not frames:
            raise EstimationError(f"{log_path}: no frame with the configured sensors could be read")
        keep = frames if options.last_frames is None else frames[-options.last_frames:]
        per_frame = [(f, to_points(f)) for f in keep]
    last = per_frame[-1][0]
    # every frame's points are in the ee frame at its own time: pooled as they are (rigid grasp)
    pooled = LabelledPoints.concat([p for _, p in per_frame]).downsampled(options.voxel_m)
    return LogPoints(pooled, len(per_frame), last.index, last.stamp_ns, last.T_world_ee, last.T_world_object_gt)
