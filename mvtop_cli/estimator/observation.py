"""What a frame shows the estimator: observed object masks from its images, with the
masking backends the config names, in each sensor's region of interest.

``Observer`` runs the backends on one image. ``ObservationModel.observe`` makes one frame's
``Observation`` for the likelihood: the ROI window of every sensor around the predicted belief,
the environment meshes that occlude each camera, and the observed masks (Algorithm 1-2 for the
cameras, choosing among the backend's proposals with the belief's best particles).

Cameras use ``masking.camera`` (``classical`` by default, or ``sam_onnx`` / ``instance_onnx``):
zero-shot proposals for Algorithm 1-2 and the promptable mode; with ``topic`` the masks an
external segmenter recorded in the log are the observation (cropped to the ROI); with
``masking.camera_evidence: colour`` (and no recorded masks) each camera's observation is instead a
per-pixel object probability from colour (``masking.colour``), scored as a soft IoU. Tactile sensors use the
indentation depth topic when the log has one (undeformed pixels removed before binarising),
else ``masking.tactile`` (``difference``: the change from a no-contact reference frame, given
as ``options.reference_image`` or taken as the first tactile image of the log).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import TOPIC_BACKEND, BackendConfig, Config
from ..errors import ConfigError
from ..filter.particles import ParticleSet
from ..masking.base import MaskContext, get_backend
from ..masking.belief import belief_probability, grabcut_from_belief
from ..masking.colour import SURE_BACKGROUND, SURE_OBJECT, histogram_overlap, object_probability
from ..masking.selection import select_masks
from ..records import Frame, SensorImage
from ..render.base import PIXEL_OCCLUDER
from ..render.roi import Roi, roi_for_particles
from .contact_pixels import prior_box, surface_pixels_in_box
from .edges import EdgeImage
from .prior import GraspPriorModel
from .scene import OBJECT_ID, SceneModel
from .symmetry import SymmetryFold


def _resolve_paths(options: dict[str, Any], base: Path | None) -> dict[str, Any]:
    """Option values of keys ending in ``_path`` resolved against the config's folder."""
    out = dict(options)
    for key, value in options.items():
        if key.endswith("_path") and isinstance(value, str) and base is not None and not Path(value).is_absolute():
            out[key] = str((base / value).resolve())
    return out


def make_backend(spec: BackendConfig, cfg: Config, key: str, drop: tuple[str, ...] = ()):
    """The backend ``spec`` names, with its options (paths relative to the config file)."""
    base = cfg.source.resolve().parent if cfg.source is not None else None
    options = {k: v for k, v in _resolve_paths(spec.options, base).items() if k not in drop}
    try:
        return get_backend(spec.backend, **options)
    except ConfigError as err:
        where = f"{cfg.source}: " if cfg.source is not None else ""
        raise ConfigError(f"{where}{key}: {err}") from None


# (image, box) pairs whose camera proposals ``Observer.camera_proposals`` keeps: two cameras' worth
# of the current frame and of an earlier one
_PROPOSALS_KEPT = 4


class Observer:
    """Makes the observed masks of one log's frames."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.camera = make_backend(cfg.masking.camera, cfg, "masking.camera")
        self.recorded = cfg.masking.camera.backend == TOPIC_BACKEND  # masks recorded in the log
        self._tactile_spec = cfg.masking.tactile
        self._tactile = None
        self._references: dict[str, np.ndarray] = {}
        # the last few images' camera proposals: the mode check's earlier frames ask for each
        # image's proposals twice, for the observation and for each pose's own choice
        self._proposals: dict[tuple, list[np.ndarray]] = {}
        ref = cfg.masking.tactile.options.get("reference_image")
        self._reference_file = None
        if ref is not None:
            base = cfg.source.resolve().parent if cfg.source is not None else Path.cwd()
            self._reference_file = (base / ref) if not Path(ref).is_absolute() else Path(ref)

    def camera_proposals(self, img: SensorImage, roi_box: tuple[int, int, int, int]) -> list[np.ndarray]:
        """Zero-shot proposals (full-image bool masks) inside ``roi_box``; none when the box
        leaves under 2 x 2 pixels of the image (a belief at the image edge: the other
        proposals and sensors carry the frame). The backends are deterministic (re-seeded every
        call), so the proposals of the last ``_PROPOSALS_KEPT`` (image, box) pairs are kept and
        given again, read-only."""
        H, W = img.image.shape[:2]
        if min(roi_box[2], W) - max(roi_box[0], 0) < 2 or min(roi_box[3], H) - max(roi_box[1], 0) < 2:
            return []
        key = (img.sensor, img.stamp_ns, tuple(int(v) for v in roi_box))
        if key not in self._proposals:
            extras = {"recorded_mask": img.mask} if self.recorded and img.mask is not None else {}
            found = list(self.camera.proposals(img.image, MaskContext(roi_box=roi_box, extras=extras)))
            for m in found:
                m.setflags(write=False)
            if len(self._proposals) >= _PROPOSALS_KEPT:
                self._proposals.pop(next(iter(self._proposals)))
            self._proposals[key] = found
        return list(self._proposals[key])

    def recorded_mask(self, img: SensorImage) -> np.ndarray | None:
        """The object mask (full-image bool) recorded for camera image ``img`` (``topic``
        backend); None when the image carries no recorded mask."""
        return None if img.mask is None else self.camera.object_mask(img.mask)

    def camera_prompt(self, img: SensorImage, prompt_mask: np.ndarray) -> np.ndarray:
        """The object mask prompted by the CAD silhouette at the current estimate (the recorded
        mask, all False without one, with the ``topic`` backend)."""
        if self.recorded:
            m = self.recorded_mask(img)
            return m if m is not None else np.zeros(img.image.shape[:2], dtype=bool)
        return np.asarray(self.camera.prompt(img.image, prompt_mask), dtype=bool)

    def tactile_mask(self, img: SensorImage) -> np.ndarray:
        """The contact region (full-image bool mask) of one tactile image: the indentation
        depth above ``masking.tactile_depth_threshold_m`` when the log has it, else the
        tactile backend's mask."""
        if img.depth is not None:
            return np.asarray(img.depth) > self.cfg.masking.tactile_depth_threshold_m
        if self._tactile is None:
            self._tactile = make_backend(self._tactile_spec, self.cfg, "masking.tactile", drop=("reference_image",))
        ref = self._reference(img)
        return np.asarray(self._tactile.contact_mask(img.image, MaskContext(background=ref)), dtype=bool)

    def _reference(self, img: SensorImage) -> np.ndarray:
        if img.sensor not in self._references:
            if self._reference_file is not None:
                import cv2

                ref = cv2.imread(str(self._reference_file), cv2.IMREAD_COLOR)
                if ref is None:
                    raise ConfigError(f"{self._reference_file}: cannot read the tactile reference image "
                                      "(masking.tactile.options.reference_image)")
                ref = ref[:, :, ::-1]
            else:
                ref = img.image  # the first image of the sensor: the log starts before contact
            if ref.shape != img.image.shape:
                raise ConfigError(f"masking.tactile.options.reference_image: size {ref.shape[:2]} differs from "
                                  f"the {img.sensor!r} images {img.image.shape[:2]}")
            self._references[img.sensor] = np.ascontiguousarray(ref)
        return self._references[img.sensor]


@dataclass
class Observation:
    """One frame's evidence, per sensor name: the ROI window (fixed for the frame), the
    occluders ``(mesh_id, T_sensor_mesh)`` of each camera, the observed mask cropped to the
    ROI (``masks``) and the observed mask area outside the ROI in ROI pixels (``outside``),
    and with the contour term (``edges.gain``) each camera image's derivatives in its ROI
    (``gradients``: ``edges.EdgeImage``; not for a camera of ``weight`` 0). With
    ``masking.tactile_depth_tolerance_m``, each tactile sensor whose log has its depth topic
    has ``indentation``: the measured gel indentation [m] in its ROI, the deepest of the image
    pixels each ROI pixel covers (``Roi.maximum``).
    ``tactile`` and ``cameras`` name the sensors with an observed mask, in the frame's
    order; ``mask_mode`` says how the camera masks were made (``proposals``, ``prompt``,
    ``recorded`` from the log's mask topics, ``colour`` for per-pixel probabilities (h, w)
    float32 instead of bool masks, or ``none`` without cameras)."""

    rois: dict[str, Roi]
    occluders: dict[str, list]
    masks: dict[str, np.ndarray]
    outside: dict[str, float]
    tactile: list[str]
    cameras: list[str]
    mask_mode: str
    gradients: dict[str, EdgeImage] = field(default_factory=dict)
    indentation: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def sensors(self) -> list[str]:
        """Every sensor with an observed mask: tactile first, then cameras (eq. 2's order)."""
        return self.tactile + self.cameras

    def area_px(self, name: str) -> float:
        """Sensor ``name``'s observed mask area [image pixels]: the mask in its ROI (a
        probability map counts its sum) plus the part outside the ROI, at the image's scale."""
        scale = self.rois[name].scale
        return (float(np.sum(self.masks[name])) + float(self.outside[name])) / (scale * scale)

    def iou_with(self, name: str, full: np.ndarray) -> float:
        """IoU of sensor ``name``'s observed mask with a full-image mask (H, W) bool, e.g. the
        true silhouette, in ROI pixels (a soft IoU for soft evidence); what either mask holds
        outside the ROI window counts as not shared. 0 when the sensor has no observed mask in
        this frame."""
        m = self.masks.get(name)
        if m is None:
            return 0.0
        roi = self.rois[name]
        m, inside = np.asarray(m, dtype=np.float64), roi.crop(full)
        shared = m[inside].sum()
        union = m.sum() + inside.sum() - shared + roi.outside_area(full) + self.outside[name]
        return float(shared / union) if union else 1.0


@dataclass(frozen=True)
class ProposalSet:
    """One camera's belief-free evidence for comparing far-apart poses
    (``likelihood.ProposalLikelihood``): the masking backend's zero-shot proposals ``masks``
    (M, h, w) bool, cropped to ``roi``, the grasp prior's window in that camera."""

    roi: Roi
    masks: np.ndarray


class ObservationModel:
    """Makes each frame's ``Observation`` for the estimator (and the camera masks for the
    baseline). ``frame_pose(frame_name, stamp_ns)`` returns ``T_world_frame`` of a TF frame
    (gripper-mounted occluders)."""

    def __init__(self, cfg: Config, scene: SceneModel, frame_pose):
        self.cfg = cfg
        self.scene = scene
        self.frame_pose = frame_pose
        self.observer = Observer(cfg)
        self.gel_distance_m = {t.name: t.gel_distance_m for t in cfg.sensors.tactile}
        self.fold = SymmetryFold.from_config(cfg, scene.symmetries)  # the belief's mean modulo symmetries
        m = cfg.masking
        # fixed grasp-prior poses (ee frame): the prior's window in each camera, and what seeds the camera GrabCut
        # with grabcut_prompt: prior; their own generator, so the filter's draws are the same either way
        self.prior_poses = GraspPriorModel(cfg.grasp_prior, cfg.search.bound).sample(
            m.prior_samples, np.random.default_rng(cfg.filter.seed)).poses
        self._contact_pixels: dict[tuple, np.ndarray | None] = {}

    def rois(self, frame: Frame, T_ee_object: np.ndarray, sensors=None, margin_px: float = 4.0) -> dict[str, Roi]:
        """Per sensor of the frame (or of ``sensors``), the ROI window that holds the object at
        every pose of ``T_ee_object`` (N, 4, 4) with ``margin_px`` image pixels around: its
        silhouette for cameras, its gel contact for tactile."""
        out = {}
        for name in sensors if sensors is not None else {**frame.cameras, **frame.tactile}:
            tactile = name in frame.tactile
            out[name] = roi_for_particles(
                self.scene.renderer.mesh(OBJECT_ID), frame.T_sensor_object(name, T_ee_object), frame.image(name).camera,
                "tactile" if tactile else "silhouette", self.gel_distance_m[name] if tactile else None,
                max_side=self.cfg.filter.tactile_roi_size_px if tactile else self.cfg.filter.roi_size_px,
                margin_px=margin_px,
            )
        return out

    def occluders(self, img: SensorImage) -> list:
        """The environment meshes ``(mesh_id, T_sensor_mesh)`` in front of camera image ``img``."""
        return self.scene.occluders(img.T_world_sensor, lambda fr: self.frame_pose(fr, img.stamp_ns))

    def camera_occluders(self, frame: Frame, name: str) -> list:
        """What hides the part from camera ``name`` in this frame: the environment meshes
        (``occluders``), plus with ``masking.contact_exclusion_m`` the pixels of the surfaces it
        may touch (``contact_pixels``) as a pixel occluder."""
        img = frame.cameras[name]
        occ = self.occluders(img)
        excluded = self.contact_pixels(frame, name)
        return occ if excluded is None else occ + [(PIXEL_OCCLUDER, excluded)]

    def contact_pixels(self, frame: Frame, name: str) -> np.ndarray | None:
        """The pixels (H, W) bool of camera ``name`` that carry no evidence of the part's outline
        in this frame, or None (``masking.contact_exclusion_m`` null, no such pixel, or a surface
        that does not look like the part): where the nearest surface seen is a world-fixed
        environment mesh that collides (the receptacle) within ``contact_exclusion_m`` of the
        box the grasp prior's fixed poses span (``contact_pixels.surface_pixels_in_box``; in the
        end effector's frame, so no belief enters it), in a frame where that surface shows the
        part's colours (``_looks_like_the_part``). There the part meets the surface it rests on;
        a part and receptacle of one colour show no outline between them, and a mask takes in
        the surface or not by chance. Excluded from the observed masks and, as an occluder,
        from every pose's render, they count for no pose. Kept for the frame's stamp."""
        margin = self.cfg.masking.contact_exclusion_m
        if margin is None:
            return None
        img = frame.cameras[name]
        key = (name, img.stamp_ns, frame.stamp_ns)
        if key not in self._contact_pixels:
            if len(self._contact_pixels) > 16:
                self._contact_pixels.clear()
            self._contact_pixels[key] = self._contact_pixels_of(frame, name, img, margin)
        return self._contact_pixels[key]

    def _contact_pixels_of(self, frame: Frame, name: str, img: SensorImage, margin_m: float) -> np.ndarray | None:
        """``contact_pixels`` of camera image ``img`` (not cached)."""
        box = prior_box(self.scene.object_mesh.bounds, frame.T_world_ee_at(img) @ self.prior_poses, margin_m)
        occluders = self.occluders(img)
        surface = surface_pixels_in_box(self.scene, img, occluders, box)
        if surface is None or not self._looks_like_the_part(frame, name, img, occluders, surface):
            return None
        return surface

    def _looks_like_the_part(self, frame: Frame, name: str, img: SensorImage, occluders: list,
                             surface: np.ndarray) -> bool:
        """Whether the environment pixels ``surface`` (H, W) bool near the part show the part's
        colours in camera image ``img``: the colour histograms (``masking.colour_bins``) of the
        pixels every fixed grasp-prior pose covers (the part) and of the ``surface`` pixels none
        covers (the surface beside it) overlap by at least ``masking.contact_exclusion_overlap``
        (Bhattacharyya coefficient). False when either set is empty (nothing to compare)."""
        roi, coverage = self.prior_coverage(frame, name, img, occluders)
        part = coverage >= SURE_OBJECT
        beside = roi.crop(surface) & (coverage < SURE_BACKGROUND)
        if not part.any() or not beside.any():
            return False
        overlap = histogram_overlap(roi.image(img.image), part, beside, self.cfg.masking.colour_bins)
        return overlap >= self.cfg.masking.contact_exclusion_overlap

    def clear_contact_pixels(self, frame: Frame, name: str, full: np.ndarray) -> np.ndarray:
        """Camera ``name``'s full-image mask or probability map (H, W) without its contact pixels
        (``contact_pixels``): they hold no evidence, for any pose."""
        excluded = self.contact_pixels(frame, name)
        if excluded is None:
            return full
        out = np.array(full, copy=True)
        out[excluded] = False if out.dtype == bool else 0
        return out

    def observe(self, frame: Frame, belief: ParticleSet, converged: bool) -> Observation:
        """The frame's observation, ROIs and occluders from the predicted ``belief``;
        camera masks prompted at the belief's mean when ``converged`` (the paper's
        promptable mode), else chosen among the proposals (Algorithm 1-2)."""
        rois = self.rois(frame, belief.poses)
        occluders = {name: [] if name in frame.tactile else self.camera_occluders(frame, name)
                     for name in {**frame.cameras, **frame.tactile}}
        masks, outside, indentation = {}, {}, {}
        for name, img in frame.tactile.items():
            full = self.observer.tactile_mask(img)
            masks[name], outside[name] = rois[name].crop(full), rois[name].outside_area(full)
            if img.depth is not None and self.cfg.masking.tactile_depth_tolerance_m is not None:
                indentation[name] = rois[name].maximum(img.depth)
        mask_mode = "none"
        if frame.cameras and self.observer.recorded:
            mask_mode = "recorded"
            for name, img in frame.cameras.items():
                full = self.observer.recorded_mask(img)
                if full is not None:
                    full = self.clear_contact_pixels(frame, name, full)
                    masks[name], outside[name] = rois[name].crop(full), rois[name].outside_area(full)
        elif frame.cameras and self.cfg.masking.camera_evidence == "colour":
            mask_mode = "colour"
            for name, m in self.colour_maps(frame, frame.cameras, rois, occluders).items():
                masks[name], outside[name] = m
        elif frame.cameras:
            if converged:
                mean = belief.mean() if self.fold is None else belief.spread(self.fold).mean
                cam_masks = {n: None if m is None else (m, 0.0)
                             for n, m in self.prompted_masks(frame, rois, occluders, mean).items()}
                mask_mode = "prompt"
            else:
                w = belief.weights()
                idx = np.argsort(-w, kind="stable")[: self.cfg.masking.candidates]
                cam_masks = self.camera_masks(frame, frame.cameras, rois, occluders, belief.poses[idx], w[idx],
                                              self.cfg.filter.seed)
                mask_mode = "proposals"
            for name, m in cam_masks.items():
                if m is not None:
                    masks[name], outside[name] = m
        gradients = {}
        if self.cfg.edges.gain > 0:
            off = {c.name for c in self.cfg.sensors.cameras if c.weight == 0}  # a camera switched off
            for name, img in frame.cameras.items():
                if name not in off:
                    gradients[name] = EdgeImage.of(img.image, rois[name], self.cfg.edges.blur_sigma_px)
        return Observation(rois, occluders, masks, outside, [n for n in frame.tactile if n in masks],
                           [n for n in frame.cameras if n in masks], mask_mode, gradients, indentation)

    def camera_masks(self, frame: Frame, cameras: dict[str, SensorImage], rois: dict[str, Roi], occluders: dict,
                     candidates: np.ndarray, weights: np.ndarray, seed: int) -> dict[str, tuple[np.ndarray, float]]:
        """Observed masks of ``cameras`` by Algorithm 1-2, each as its ROI crop and its area
        outside the ROI (ROI pixels): each camera's proposals from the backend plus one GrabCut
        proposal, chosen jointly by how well the candidate poses ``T_ee_object`` (P, 4, 4) with
        ``weights`` (P,) explain them. The GrabCut is seeded by the candidates' weighted
        silhouettes (``masking.grabcut_prompt: belief``) or, with ``prior``, by the fixed
        grasp-prior poses: then every proposal is made in the prior's window from the image
        alone, and the candidates only choose among them. A camera whose proposals all fail is
        left out. With masks recorded in the log (``topic``) these are the observed masks."""
        if self.observer.recorded:
            full = {name: self.observer.recorded_mask(img) for name, img in cameras.items()}
            full = {name: self.clear_contact_pixels(frame, name, m) for name, m in full.items() if m is not None}
            return {name: (rois[name].crop(m), rois[name].outside_area(m)) for name, m in full.items()}
        proposals, outside, rendered = {}, {}, {}
        for name, img in cameras.items():
            roi = rois[name]
            rendered[name] = self.scene.renderer.render_masks(
                OBJECT_ID, frame.T_sensor_object(name, candidates), img.camera, roi, occluders[name])
            if self.cfg.masking.grabcut_prompt == "belief":
                prompt_roi, probability = roi, belief_probability(rendered[name], weights)
                band_px = self.cfg.masking.belief_band_px  # the belief's own outline is left to the image
            else:
                prompt_roi, probability = self.prior_coverage(frame, name, img, occluders[name])
                band_px = 0  # the prior's poses spread wider than any band: no outline of the belief to free
            box = (prompt_roi.x0, prompt_roi.y0, prompt_roi.x0 + prompt_roi.width, prompt_roi.y0 + prompt_roi.height)
            props = list(self.observer.camera_proposals(img, box))
            grabcut = grabcut_from_belief(prompt_roi.image(img.image), probability, seed=seed, band_px=band_px)
            if grabcut is not None:
                props.insert(0, prompt_roi.paste(grabcut, img.image.shape[:2], fill=False))
            props = [self.clear_contact_pixels(frame, name, p) for p in props]
            proposals[name] = [roi.crop(p) for p in props]
            outside[name] = [roi.outside_area(p) for p in props]
        chosen = select_masks(proposals, rendered, {n: 1.0 for n in cameras})
        return {name: (m, outside[name][int(chosen.per_sensor_choice[name][chosen.best_pose_index])])
                for name, m in chosen.masks.items() if m is not None}

    def proposal_sets(self, frame: Frame) -> dict[str, ProposalSet]:
        """Per camera of the frame with zero-shot proposals, the backend's proposals in the grasp
        prior's window (its fixed poses' ROI), made from the image alone (no GrabCut prompt, no
        belief): what ``likelihood.ProposalLikelihood`` lets each pose choose from. Empty with
        recorded masks (``topic``) or colour evidence: those are free of the belief already."""
        if self.observer.recorded or self.cfg.masking.camera_evidence == "colour":
            return {}
        out = {}
        for name, img in frame.cameras.items():
            roi = self.prior_window(frame, name)
            box = (roi.x0, roi.y0, roi.x0 + roi.width, roi.y0 + roi.height)
            found = self.observer.camera_proposals(img, box)
            if found:
                out[name] = ProposalSet(roi, np.stack([roi.crop(self.clear_contact_pixels(frame, name, p))
                                                       for p in found]))
        return out

    def prior_window(self, frame: Frame, name: str, margin_px: float = 4.0) -> Roi:
        """The grasp prior's window in camera ``name``: the ROI of its fixed poses with
        ``margin_px`` image pixels around."""
        return self.rois(frame, self.prior_poses, [name], margin_px)[name]

    def prior_coverage(self, frame: Frame, name: str, img: SensorImage, occluders: list,
                       margin_px: float = 4.0) -> tuple[Roi, np.ndarray]:
        """The grasp prior's window in camera ``name`` (``prior_window``) and the fraction (h, w)
        of those poses' silhouettes, behind the occluders, covering each pixel."""
        roi = self.prior_window(frame, name, margin_px)
        rendered = self.scene.renderer.render_masks(OBJECT_ID, frame.T_sensor_object(name, self.prior_poses),
                                                    img.camera, roi, occluders)
        return roi, belief_probability(rendered, np.ones(len(rendered)))

    def colour_maps(self, frame: Frame, cameras: dict[str, SensorImage], rois: dict[str, Roi],
                    occluders: dict) -> dict[str, tuple[np.ndarray, float]]:
        """Soft camera evidence (``masking.camera_evidence: colour``): per camera, each pixel's
        object probability from colour histograms learned where the grasp prior places the part
        (``masking.colour``), averaged into the ROI ``rois[name]`` (h, w) float32, and its sum
        outside the ROI (ROI pixels). A camera whose prior window holds no object or no
        background pixel is left out."""
        out = {}
        for name, img in cameras.items():
            prior_roi, coverage = self.prior_coverage(frame, name, img, occluders[name],
                                                      self.cfg.masking.colour_margin_px)
            window = object_probability(prior_roi.image(img.image), coverage, self.cfg.masking.colour_bins)
            if window is not None:
                full = prior_roi.paste(window, img.image.shape[:2], fill=np.float32(0.0))
                full = self.clear_contact_pixels(frame, name, full)
                out[name] = (rois[name].average(full), rois[name].outside_sum(full))
        return out

    def prompted_masks(self, frame: Frame, rois: dict[str, Roi], occluders: dict,
                       T_ee_object: np.ndarray) -> dict[str, np.ndarray | None]:
        """The paper's promptable mode: each camera's mask prompted by the CAD silhouette at
        ``T_ee_object`` (4, 4), cropped to its ROI (None where the silhouette is empty)."""
        out = {}
        for name, img in frame.cameras.items():
            full = Roi.full(img.camera)
            prompt = self.scene.renderer.render_masks(OBJECT_ID, frame.T_sensor_object(name, T_ee_object)[None],
                                                      img.camera, full, occluders[name])[0]
            if not prompt.any():
                out[name] = None
                continue
            mask = self.clear_contact_pixels(frame, name, self.observer.camera_prompt(img, prompt))
            out[name] = rois[name].crop(mask)
        return out
