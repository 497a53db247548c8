"""``mvtop estimate``: run the M-VTOP particle filter over a log and write the pose track.

Per frame (paper section IV): observed masks from the masking backends (Algorithm 1-2 for
cameras over the classical and belief-prompted proposals; the tactile depth topic), then the
particle filter (Algorithm 3): motion model (Algorithm 4), weights from the visuo-tactile
score (eq. 1-2) times the contact likelihood (eq. 8-9), tempered refinement within the frame,
resampling, and the weighted-mean estimate.

Search. The first frame starts with two independent cross-entropy searches of the grasp
prior (multi-start: one search alone sometimes settles in a wrong mode, e.g. the cube 10
degrees off); every later frame checks with a short local search whether the belief sits at
the likelihood's peak and redoes the frame from the searched poses when it clearly does not.
"""

from __future__ import annotations

import contextlib
import json
import signal
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..config import Config, dump_config
from ..contact.likelihood import log_contact_likelihood
from ..errors import EstimationError, MvtopError
from ..filter.motion import MotionModel, init_from_prior, init_uniform_box, perturb_about_origin
from ..filter.particles import ParticleSet, ess_from_log_weights
from ..filter.resampling import resample
from ..filter.search import cross_entropy_search
from ..filter.health import (
    SensorConsistency, check_jump, count_warnings, jump_warning, sensor_report, step_warnings, warning, warning_lines,
)
from ..filter.pf import ParticleFilter
from ..filter.scoring import visuo_tactile_score
from ..geometry import se3
from ..io.atomic import atomic_output
from ..io.frames import LogTopics, SensorTopics, FrameReader
from ..io.mcap_reader import McapLog
from ..io.mcap_writer import LogWriter
from ..io.track_scene import object_triangles, write_track_scene
from ..masking.belief import belief_probability, grabcut_from_belief
from ..masking.selection import select_masks
from ..records import Frame, SensorImage
from ..render.roi import Roi, roi_for_particles
from .checkpoint import Checkpoint, EstimateInterrupted, Restored, fingerprint
from .observe import TACTILE_DEPTH_THRESHOLD_M, Observer
from .scene_model import OBJECT_ID, SceneModel

_CANDIDATES = 96  # candidate poses for Algorithm 1 (mask selection)
_CONVERGED_TRANSLATION_M = 5e-4  # belief spread below which cameras may switch to prompt mode
_CONVERGED_ROTATION_RAD = np.radians(1.5)
# The paper's promptable mode (camera masks prompted at the converged estimate) is off by
# default (config masking.prompt_when_converged): on the
# sample logs its masks follow the estimate (a self-confirming bias) and lose the object's
# thin or low-contrast parts near the receptacle; e.g. shaft_peg drifted 1-4 mm along its
# axis during contact with it, 0.3-0.5 mm without (ground-truth IoU of the prompted masks
# 0.74-0.85 vs 0.96-0.99 for Algorithm 1-2 over the proposals).
_PARTICLES_IN_TRACK = 200  # particles written per frame to track.mcap
_INIT_FACTOR = 6  # prior samples per particle in each of the first frame's coarse searches
_FIRST_FRAME_ITERATION_FACTOR = 3  # refine iterations on the first frame (and after a re-search)
_TACTILE_SHARE = 0.5
# Re-search check (see Estimator._filter_frame): a short cross-entropy search from the belief
# widened by these sigmas; a frame is redone from the searched population when the search
# beats the estimate and the best particle by more than _RESEARCH_MARGIN nats.
_RESEARCH = True
_CHECK_SIGMA_TRANSLATION_M = 1e-3
_CHECK_SIGMA_ROTATION_RAD = float(np.radians(3.0))
_CHECK_ROUNDS = 3
_RESEARCH_MARGIN = 10.0
# The searches stay within this many times the grasp prior's half-widths of the nominal grasp
# (twice as many sigmas for a gaussian prior): room for slip beyond the prior, no more.
_SEARCH_BOUND = 2.0
# Failure handling (see filter/health.py and docs/robustness.md): a frame whose effective
# sample size collapsed is redone with this many tempering iterations (or 3x its own).
_COLLAPSE_RETRY_ITERATIONS = 24


@dataclass(frozen=True)
class EstimateOptions:
    """Command-line overrides of the config."""

    modalities: tuple[str, ...] | None = None
    num_particles: int | None = None
    seed: int | None = None
    max_frames: int | None = None


@dataclass
class FrameEstimate:
    """The filter's output for one frame."""

    index: int
    stamp_ns: int
    T_ee_object: np.ndarray
    T_world_object: np.ndarray
    covariance: np.ndarray  # (6, 6): x, y, z [m], rx, ry, rz [rad] about the mean, ee axes
    ess: float
    contact: bool | None
    sensors: tuple[str, ...]
    flags: tuple[str, ...]
    mask_mode: str
    particles_world: np.ndarray = field(repr=False)
    T_world_object_gt: np.ndarray | None = None
    # failure modes detected in this frame (filter.health.warning records)
    warnings: tuple[dict, ...] = ()
    # per sensor: IoU of its observed mask with the mask rendered at the estimate
    sensor_iou: dict[str, float] = field(default_factory=dict)
    # the sensor consistency watch after this frame (``Estimator.restore_consistency`` on resume)
    consistency: dict = field(default_factory=dict)


def sensor_topics(cfg: Config) -> list[SensorTopics]:
    """The reader's view of the config's sensors (honouring the enabled modalities)."""
    out = []
    if "vision" in cfg.modalities:
        out += [SensorTopics(c.name, "camera", c.image_topic, c.info_topic, None, c.frame) for c in cfg.sensors.cameras]
    if "tactile" in cfg.modalities:
        out += [
            SensorTopics(t.name, "tactile", t.image_topic, t.info_topic, t.depth_topic, t.frame)
            for t in cfg.sensors.tactile
        ]
    return out


def log_topics(cfg: Config) -> LogTopics:
    t = cfg.topics
    return LogTopics(
        tf=t.tf, tf_static=t.tf_static, contact=t.contact if "contact" in cfg.modalities else None,
        joint_states=t.joint_states, ground_truth=t.ground_truth, world_frame=cfg.frames.world,
        ee_frame=cfg.frames.ee, sync_tolerance_ns=int(round(cfg.sync_tolerance_s * 1e9)),
        wrench=t.wrench if "contact" in cfg.modalities else None,
        contact_force_on_n=cfg.contact.force_on_n, contact_force_off_n=cfg.contact.force_off_n,
        urdf=None if cfg.robot.urdf is None else str(cfg.robot.urdf),
    )


class Estimator:
    """The M-VTOP filter over a stream of frames (no io: frames in, estimates out)."""

    def __init__(self, cfg: Config, scene: SceneModel, frame_pose: Callable[[str, int], np.ndarray]):
        self.cfg = cfg
        self.scene = scene
        self.frame_pose = frame_pose
        f = cfg.filter
        self.rng = np.random.default_rng(f.seed)
        self.motion = MotionModel(
            f.sigma_low_translation_m, np.radians(f.sigma_low_rotation_deg),
            f.sigma_high_translation_m, np.radians(f.sigma_high_rotation_deg),
        )
        self.pf = ParticleFilter(self.motion, f.resampling, f.ess_threshold, self.rng, refine_iterations=f.refine_iterations,
                                 collapse_retry_iterations=_COLLAPSE_RETRY_ITERATIONS)
        # per-sensor agreement with the others; scales eq. 1-2 weights of a sensor that keeps disagreeing
        self.consistency = SensorConsistency()
        self.observer = Observer(cfg)
        self.particles: ParticleSet | None = None
        self.tactile_cfg = {t.name: t for t in cfg.sensors.tactile}
        self.camera_weights = {c.name: c.weight for c in cfg.sensors.cameras}
        self.use_contact = "contact" in cfg.modalities
        # cameras and tactile sensors both enabled: eq. 2's weights split between them
        self.fuses_both = ("vision" in cfg.modalities and bool(cfg.sensors.cameras)
                           and "tactile" in cfg.modalities and bool(cfg.sensors.tactile))

    def _init_particles(self) -> ParticleSet:
        g = self.cfg.grasp_prior
        n = self.cfg.filter.num_particles
        T_nom = g.pose.matrix()
        if g.distribution == "uniform":
            return init_uniform_box(T_nom, g.translation_m, np.radians(g.rotation_deg), n, self.rng)
        return init_from_prior(T_nom, g.translation_m, np.radians(g.rotation_deg), n, self.rng)

    def _prior_samples(self, m: int) -> np.ndarray:
        g = self.cfg.grasp_prior
        T_nom = g.pose.matrix()
        if g.distribution == "uniform":
            return init_uniform_box(T_nom, g.translation_m, np.radians(g.rotation_deg), m, self.rng).poses
        return init_from_prior(T_nom, g.translation_m, np.radians(g.rotation_deg), m, self.rng).poses

    def _tempered_resample(self, poses: np.ndarray, ll: np.ndarray) -> ParticleSet:
        """N particles from a scored search population: weights ``L^b`` with the largest
        ``b`` that keeps an effective sample size of N, then resampling."""
        n = self.cfg.filter.num_particles
        finite = np.isfinite(ll)
        ll = np.where(finite, ll - np.max(ll[finite]), -np.inf) if finite.any() else ll
        lo, hi = 0.0, 1.0
        for _ in range(30):  # largest tempering exponent that keeps ESS >= n (0: uniform over the finite)
            mid = 0.5 * (lo + hi)
            if ess_from_log_weights(mid * ll) >= n:
                lo = mid
            else:
                hi = mid
        weighted = ParticleSet(poses, np.where(finite, lo * np.where(finite, ll, 0.0), -np.inf))
        return resample(weighted, self.cfg.filter.resampling, self.rng, n_out=n)

    def _initial_search(self, log_likelihood) -> ParticleSet:
        """Coarse search of the grasp prior on the first frame (Algorithm 1's pose
        candidates): draw ``_INIT_FACTOR`` times more prior samples than particles, move them
        towards the likelihood's basin by a cross-entropy search, weight them by the
        likelihood tempered to keep an effective sample size of N, and resample N. The
        frame's refinement then starts from the basin of the likelihood instead of from the
        whole prior, which a few hundred particles cannot cover at sub-millimetre scale."""
        n = self.cfg.filter.num_particles
        poses, ll = cross_entropy_search(self._prior_samples(n * _INIT_FACTOR), log_likelihood, self.rng)
        if not np.isfinite(ll).any():
            return self._init_particles()
        return self._tempered_resample(poses, ll)

    def _local_search(self, particles: ParticleSet, log_likelihood) -> tuple[np.ndarray, np.ndarray]:
        """A short cross-entropy search started from the belief widened by
        ``_CHECK_SIGMA_*``: the likelihood's best pose near the belief, to check whether the
        belief sits at the likelihood's peak (a wrong or lagging mode shows as a pose that
        fits the observation much better than any particle)."""
        n = len(particles)
        idx = self.rng.integers(0, n, n)
        dt = self.rng.standard_normal((n, 3)) * _CHECK_SIGMA_TRANSLATION_M
        dw = self.rng.standard_normal((n, 3)) * _CHECK_SIGMA_ROTATION_RAD
        start = perturb_about_origin(particles.poses[idx], dt, dw)
        return cross_entropy_search(start, log_likelihood, self.rng, rounds=_CHECK_ROUNDS)

    def _within_prior(self, T_ee_obj: np.ndarray) -> np.ndarray:
        """(N,) bool: poses within ``_SEARCH_BOUND`` times the grasp prior's half-widths
        (uniform) or sigmas (gaussian) of the nominal grasp, per ee axis."""
        g = self.cfg.grasp_prior
        T_nom = g.pose.matrix()
        dt = np.abs(T_ee_obj[:, :3, 3] - T_nom[:3, 3])
        dw = np.abs(se3.matrix_to_rotvec(T_ee_obj[:, :3, :3] @ T_nom[:3, :3].T))
        k = _SEARCH_BOUND if g.distribution == "uniform" else 2.0 * _SEARCH_BOUND
        return np.all(dt <= k * g.translation_m, axis=1) & np.all(dw <= k * np.radians(g.rotation_deg), axis=1)

    def _bounded(self, log_likelihood):
        """``log_likelihood`` restricted to the grasp prior's region: the searches draw from
        Gaussians fitted to their elites, which a likelihood that is flat in some direction
        (one modality alone) lets wander far outside any plausible grasp."""

        def fn(T_ee_obj: np.ndarray) -> np.ndarray:
            return np.where(self._within_prior(T_ee_obj), log_likelihood(T_ee_obj), -np.inf)

        return fn

    def _filter_frame(self, ps: ParticleSet, first: bool, contact, log_likelihood):
        """Predict + refine (first frame: global search + refine), then the re-search check:
        if a search finds a pose whose log-likelihood beats both the estimate and the best
        particle by ``_RESEARCH_MARGIN`` nats, the belief missed the likelihood's peak (a
        wrong mode from the first frame, or slip faster than the motion model); the frame is
        then redone from the searched population and its result kept if its estimate fits
        better."""
        f = self.cfg.filter
        search_ll = self._bounded(log_likelihood)
        predicted = self._initial_search(search_ll) if first else self.pf.predict(ps, bool(contact))
        iterations = f.refine_iterations * (_FIRST_FRAME_ITERATION_FACTOR if first else 1)
        result = self.pf.refine(predicted, log_likelihood, iterations, self.pf.refine_shrink)
        if not _RESEARCH:
            return result
        if first:  # multi-start: a second, independent global search
            poses, ll = cross_entropy_search(self._prior_samples(f.num_particles * _INIT_FACTOR), search_ll, self.rng)
        else:
            poses, ll = self._local_search(result.particles, search_ll)
        if not np.isfinite(ll).any():
            return result
        best = poses[int(np.argmax(ll))]
        cur = result.particles.poses
        ref = cur[int(np.argmax(log_likelihood(cur)))]
        cmp = log_likelihood(np.stack([result.estimate, ref, best]))
        if cmp[2] - max(cmp[0], cmp[1]) <= _RESEARCH_MARGIN:
            return result
        alt = self.pf.refine(self._tempered_resample(poses, ll), log_likelihood,
                             f.refine_iterations * _FIRST_FRAME_ITERATION_FACTOR, self.pf.refine_shrink)
        cmp2 = log_likelihood(np.stack([result.estimate, alt.estimate]))
        if cmp2[1] > cmp2[0]:
            alt.diagnostics.setdefault("flags", []).append("re_searched")
            return alt
        return result

    # --- observed masks ------------------------------------------------------------------

    def _tactile_mask(self, img: SensorImage) -> np.ndarray:
        return self.observer.tactile_mask(img)

    def _camera_masks(self, frame: Frame, rois: dict[str, Roi], occluders: dict, converged: bool) -> tuple[dict, str]:
        """Observed camera masks in each camera's ROI: Algorithm 1-2 over the classical
        proposals plus the belief-prompted GrabCut proposal, or prompted at the estimate once
        the belief has converged (the paper's promptable mode)."""
        ps = self.particles
        cams = frame.cameras
        if converged:
            est = ps.mean()
            out = {}
            for name, img in cams.items():
                T = se3.invert(img.T_world_sensor) @ (_ee_at(img, frame) @ est)
                full = Roi.full(img.camera)
                prompt = self.scene.renderer.render_masks(OBJECT_ID, T[None], img.camera, full, occluders[name])[0]
                out[name] = rois[name].crop(self.observer.camera_prompt(img, prompt)) if prompt.any() else None
            return out, "prompt"
        w = ps.weights()
        idx = np.argsort(-w, kind="stable")[:_CANDIDATES]
        cand = ps.poses[idx]
        proposals, rendered = {}, {}
        for name, img in cams.items():
            roi = rois[name]
            T = se3.invert(img.T_world_sensor) @ (_ee_at(img, frame) @ cand)
            rendered[name] = self.scene.renderer.render_masks(OBJECT_ID, T, img.camera, roi, occluders[name])
            box = (roi.x0, roi.y0, roi.x0 + roi.width, roi.y0 + roi.height)
            props = [roi.crop(p) for p in self.observer.camera_proposals(img, box)]
            prob = belief_probability(rendered[name], w[idx])
            belief = grabcut_from_belief(roi_image(img.image, roi), prob, seed=self.cfg.filter.seed)
            proposals[name] = ([belief] if belief is not None else []) + props
        sel = select_masks(proposals, rendered, {n: 1.0 for n in cams})
        return dict(sel.masks), "proposals"

    # --- one frame -------------------------------------------------------------------------

    def step(self, frame: Frame) -> FrameEstimate:
        """One frame: masks, filter update, and the failure checks of filter/health.py; the
        estimate is checked against the previous frame's belief and the motion model
        (``estimate_jump``)."""
        previous = None if self.particles is None else self.particles.spread()
        out = self._step(frame)
        if previous is not None:
            contact = bool(frame.contact) if self.use_contact else False
            sigma_t, sigma_r = self.motion.sigmas(contact)
            jump = check_jump(previous, out.T_ee_object, sigma_t, sigma_r, self.pf.jump_sigmas,
                              self.pf.floor_translation_m, self.pf.floor_rotation_rad)
            if jump.jumped:
                cause = "the belief was re-searched" if "re_searched" in out.flags else ""
                out = replace(out, warnings=out.warnings + (jump_warning(frame.index, jump, self.pf.jump_sigmas, cause),),
                              flags=out.flags + ("estimate_jump",))
        return out

    def _step(self, frame: Frame) -> FrameEstimate:
        """``step`` without the jump check."""
        first = self.particles is None
        if first:
            self.particles = self._init_particles()
        ps = self.particles
        contact = frame.contact if self.use_contact else None
        f = self.cfg.filter
        T_world_ee = frame.T_world_ee
        spread = ps.spread()
        converged = self.cfg.masking.prompt_when_converged and (not first) and spread.translation_rms_m < _CONVERGED_TRANSLATION_M and spread.rotation_rms_rad < _CONVERGED_ROTATION_RAD

        # ROIs and occluders from the predicted belief (fixed for the frame).
        occluders, rois, observed, cams = {}, {}, {}, {}
        for name, img in {**frame.cameras, **frame.tactile}.items():
            tactile = name in frame.tactile
            T = se3.invert(img.T_world_sensor) @ (_ee_at(img, frame) @ ps.poses)
            mode = "tactile" if tactile else "silhouette"
            gel = self.tactile_cfg[name].gel_distance_m if tactile else None
            rois[name] = roi_for_particles(self.scene.renderer.mesh(OBJECT_ID), T, img.camera, mode, gel, max_side=f.roi_size_px)
            occluders[name] = [] if tactile else self.scene.occluders(img.T_world_sensor, lambda fr: self.frame_pose(fr, img.stamp_ns))
        crops, outside = {}, {}
        for name, img in frame.tactile.items():
            full = self._tactile_mask(img)
            crops[name], outside[name] = rois[name].crop(full), rois[name].outside_area(full)
        mask_mode = "none"
        if frame.cameras:
            cam_masks, mask_mode = self._camera_masks(frame, rois, occluders, converged)
            for name, m in cam_masks.items():
                if m is not None:
                    crops[name], outside[name] = m, 0.0
        self.last_masks = {n: (rois[n], crops[n]) for n in crops}

        tac_names = [n for n in frame.tactile if n in crops]
        cam_names = [n for n in frame.cameras if n in crops]
        # each modality keeps its share of eq. 2 on frames where the other one has no image
        # (sensors at different rates): rescaling touch to the whole score on tactile-only
        # frames let the pads pull the rotations they cannot place
        t_share, v_share = (_TACTILE_SHARE, 1.0 - _TACTILE_SHARE) if self.fuses_both else (1.0, 1.0)
        base_gamma = eq2_weights([self.tactile_cfg[n].weight for n in tac_names], t_share)
        base_nu = eq2_weights([self.camera_weights[n] for n in cam_names], v_share)

        def ious(T_ee_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            iou_t = np.empty((len(T_ee_obj), len(tac_names)))
            iou_v = np.empty((len(T_ee_obj), len(cam_names)))
            for j, n in enumerate(tac_names):
                img = frame.tactile[n]
                T = se3.invert(img.T_world_sensor) @ (_ee_at(img, frame) @ T_ee_obj)
                iou_t[:, j] = self.scene.renderer.score_masks(
                    OBJECT_ID, T, img.camera, rois[n], crops[n], mode="tactile",
                    gel_distance_m=self.tactile_cfg[n].gel_distance_m,
                    penetration_threshold_m=TACTILE_DEPTH_THRESHOLD_M, observed_outside=outside[n],
                )
            for j, n in enumerate(cam_names):
                img = frame.cameras[n]
                T = se3.invert(img.T_world_sensor) @ (_ee_at(img, frame) @ T_ee_obj)
                iou_v[:, j] = self.scene.renderer.score_masks(
                    OBJECT_ID, T, img.camera, rois[n], crops[n], occluders[n], observed_outside=outside[n]
                )
            return iou_t, iou_v

        scored = {"invalid": 0, "evaluated": 0}

        def make_log_likelihood(gamma: np.ndarray, nu: np.ndarray):
            def log_likelihood(T_ee_obj: np.ndarray) -> np.ndarray:
                iou_t, iou_v = ious(T_ee_obj)
                # eq. 1-2 without the softmax's normalisation over the batch (a constant for
                # one batch, but poses scored in different calls are compared: Metropolis
                # ratios, search elites), so log-likelihoods of different calls agree.
                # the weights are each present sensor's share of a full frame (base_gamma, base_nu):
                # kept as they are, not rescaled to the sensors of this frame
                score = visuo_tactile_score(iou_t, iou_v, gamma if len(gamma) else None, nu if len(nu) else None,
                                            renormalise=False) / f.temperature
                if contact and self.scene.has_contact_model:
                    phi = self.scene.phi(T_world_ee @ T_ee_obj)
                    score = score + log_contact_likelihood(phi, True, self.cfg.contact.margin_m, self.cfg.contact.softness_m)
                # NaN / +inf (a degenerate render or distance) mean "no valid score": weight zero,
                # never a NaN carried into comparisons, searches or the estimate
                bad = np.isnan(score) | np.isposinf(score)
                scored["invalid"] += int(bad.sum())
                scored["evaluated"] += len(score)
                return np.where(bad, -np.inf, score) if bad.any() else score

            return log_likelihood

        gamma, nu = self._weighted(tac_names, base_gamma), self._weighted(cam_names, base_nu)
        log_likelihood = make_log_likelihood(gamma, nu)
        # kept for diagnostics: the likelihood (and IoUs) at any pose, e.g. the ground truth's
        self.last_log_likelihood, self.last_ious = log_likelihood, ious
        has_obs = bool(tac_names or cam_names)
        result = self._filter_update(ps, first, contact, has_obs, log_likelihood)
        warnings = step_warnings(frame.index, _with_counts(result.diagnostics, scored), f.num_particles)
        flags = [fl for fl in result.flags if fl != "estimate_jump"]  # ``step`` checks the jump against the last frame

        # a sensor that keeps disagreeing with all the others gets its weight scaled down from
        # the next frame on; if its pull had biased the belief, the other sensors draw it back
        # through the filter and the re-search check (restarting from the grasp prior at that
        # frame was no better on logs with one pad's image flipped: conn1 3.9 deg against 1.5
        # deg this way after 14 frames, conn2 2.5 against 3.7)
        sensor_iou, informative = self._agreement(result.estimate, ious, tac_names + cam_names, crops, outside,
                                                  np.concatenate([base_gamma, base_nu]))
        for name, iou, others in self.consistency.observe(sensor_iou, informative):
            what = "tactile sensor" if name in tac_names else "camera"
            warnings.append(warning(
                frame.index, "sensor_downweighted",
                f"{what} {name!r} disagreed with the other sensors for {self.consistency.frames} frames in a row "
                f"(IoU of its mask at the estimate {iou:.2f}, the others' median {others:.2f}): its weight is "
                f"scaled by {self.consistency.factor:g} from frame {frame.index + 1} on",
                sensor=name, iou_at_estimate=iou, others_median_iou=others, weight_factor=self.consistency.factor,
            ))
            flags.append("sensor_downweighted")

        self.particles = result.particles
        est = result.estimate
        keep = self.rng.choice(len(result.particles.poses), size=min(_PARTICLES_IN_TRACK, len(result.particles.poses)), replace=False)
        keep.sort()
        return FrameEstimate(
            index=frame.index, stamp_ns=frame.stamp_ns, T_ee_object=est, T_world_object=T_world_ee @ est,
            covariance=result.spread.covariance, ess=float(result.ess), contact=frame.contact,
            sensors=tuple(tac_names + cam_names), flags=tuple(dict.fromkeys(flags)), mask_mode=mask_mode,
            particles_world=T_world_ee @ result.particles.poses[keep], T_world_object_gt=frame.T_world_object_gt,
            warnings=tuple(warnings), sensor_iou=sensor_iou,
            consistency={"factors": dict(self.consistency.factors), "streak": dict(self.consistency.streak)},
        )

    def restore_consistency(self, state: dict) -> None:
        """Continue the sensor consistency watch from a frame's ``FrameEstimate.consistency``
        (a resumed run then scales the same sensors down at the same frames)."""
        self.consistency.factors = dict(state.get("factors", {}))
        self.consistency.streak = dict(state.get("streak", {}))

    def _filter_update(self, ps: ParticleSet, first: bool, contact, has_obs: bool, log_likelihood):
        """The frame's filter update: a plain prediction without observations, else the
        search + tempered refinement (``_filter_frame``) or Algorithm 3's single update."""
        f = self.cfg.filter
        if not has_obs and not contact:
            return self.pf.step(ps, bool(contact), lambda T: np.zeros(len(T)), refine_iterations=0)
        if f.refine_iterations > 0:
            return self._filter_frame(ps, first, contact, log_likelihood)
        predicted = self._initial_search(log_likelihood) if first else self.pf.predict(ps, bool(contact))
        return self.pf.update(predicted, log_likelihood)

    def _weighted(self, names: list[str], weights: np.ndarray) -> np.ndarray:
        """Eq. 1-2 weights (n,) of one modality's sensors with the consistency watch's
        factors applied; while a sensor of the modality keeps its full weight, the
        modality's share is kept (the others take up what a scaled-down sensor loses, as
        if it were absent)."""
        factors = np.array([self.consistency.weight_factor(n) for n in names])
        if not np.any(factors != 1.0):
            return weights
        scaled = weights * factors
        full = factors == 1.0
        if np.any(full) and scaled.sum() > 0:
            scaled[full] *= (weights.sum() - scaled[~full].sum()) / scaled[full].sum()
        return scaled

    def _agreement(self, T_ee_obj: np.ndarray, ious, names: list[str], crops: dict, outside: dict,
                   weights: np.ndarray) -> tuple[dict, dict]:
        """Per sensor: the IoU of its observed mask with the mask rendered at the estimate
        ``T_ee_obj`` (4, 4), and whether it is informative (not both masks empty, and not
        switched off by a weight of 0: such a sensor neither votes in nor is judged by the
        consistency watch)."""
        iou_t, iou_v = ious(T_ee_obj[None])
        values = np.concatenate([iou_t[0], iou_v[0]])
        iou = {n: float(v) for n, v in zip(names, values)}
        informative = {n: bool(w > 0 and (crops[n].any() or outside[n] > 0 or iou[n] < 1.0))
                       for n, w in zip(names, weights)}
        return iou, informative


def eq2_weights(configured: list[float | None], share: float) -> np.ndarray:
    """Eq. 1-2 weights (n,) of one modality's sensors present in a frame: a sensor's
    configured ``weight`` where set (0 switches the sensor off), else an equal part of the
    modality's ``share`` (1/N_T or 1/N_V of it)."""
    default = share / len(configured) if configured else 0.0
    return np.array([default if w is None else float(w) for w in configured], dtype=float)


def _ee_at(img: SensorImage, frame: Frame) -> np.ndarray:
    """The end effector in ``world`` at the time ``img`` was taken (4, 4): the held
    object is placed in each image with the gripper pose of that image's own stamp."""
    return frame.T_world_ee if img.T_world_ee is None else img.T_world_ee


def _with_counts(diagnostics: dict, scored: dict) -> dict:
    """A step's diagnostics with the invalid / evaluated counts of every likelihood call of
    the frame (searches included), which the estimator's likelihood counts itself."""
    return {**diagnostics, "invalid_log_likelihood": scored["invalid"], "evaluated_poses": scored["evaluated"]}


def roi_image(image: np.ndarray, roi: Roi) -> np.ndarray:
    """The ROI window of an (H, W, 3) uint8 image at ROI resolution (area-averaged, zero
    outside the image)."""
    import cv2

    H, W = image.shape[:2]
    win = np.zeros((roi.height, roi.width, 3), np.uint8)
    ys, xs = max(roi.y0, 0), max(roi.x0, 0)
    ye, xe = min(roi.y0 + roi.height, H), min(roi.x0 + roi.width, W)
    if ye > ys and xe > xs:
        win[ys - roi.y0 : ye - roi.y0, xs - roi.x0 : xe - roi.x0] = image[ys:ye, xs:xe]
    rows, cols = roi.shape
    if (rows, cols) == win.shape[:2]:
        return win
    interp = cv2.INTER_AREA if roi.scale < 1 else cv2.INTER_NEAREST
    return cv2.resize(win, (cols, rows), interpolation=interp)


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
    are written, and when a fresh run fails (a resumed run keeps it). Ctrl-C or
    ``checkpoint.Terminated`` (SIGTERM) raise ``checkpoint.EstimateInterrupted`` saying how
    many frames are checkpointed.
    """
    cfg = apply_options(cfg, options)
    t_start = time.perf_counter()
    sensors = sensor_topics(cfg)
    if not sensors and "contact" not in cfg.modalities:
        raise EstimationError("no sensor is enabled: check modalities and sensors in the config")
    fp = fingerprint(log_path, cfg)
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
            if ck is None:
                created = not out_dir.exists()
                out_dir.mkdir(parents=True, exist_ok=True)
                ck, restored = Checkpoint.start(out_dir, fp, resume=False)
            _run_frames(reader, estimator, ck, restored, options.max_frames, total, progress, t_start)
            skipped = list(reader.skipped)
            if not ck.frames_done:
                raise EstimationError(f"{log_path}: no frame with the configured sensors could be read")
    except KeyboardInterrupt as err:
        if ck is None:
            raise
        ck.close()
        if not ck.frames_done and not resume:  # nothing to resume: leave nothing behind
            ck.remove()
            if created:
                _remove_if_empty(out_dir)
        raise EstimateInterrupted(ck.frames_done, total, ck.dir, "frames", _signum(err)) from None
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
        summary = _summary(results, cfg, log_path, elapsed, skipped, scene.warnings)
        summary["resumed_at_frame"] = restored.frames_done
        summary["checkpoint_ms_per_frame"] = round(1e3 * ck.write_seconds / max(ck.writes, 1), 3)
        write_track(out_dir, results, cfg, summary)
    except KeyboardInterrupt as err:
        ck.close()
        raise EstimateInterrupted(len(results), total, ck.dir, "outputs", _signum(err)) from None
    ck.remove()
    return summary


def _run_frames(reader: FrameReader, estimator: Estimator, ck: Checkpoint, restored: Restored,
                max_frames: int | None, total: int, progress: Callable[[int, int], None] | None, t_start: float) -> None:
    """The frame loop: replay the ``restored.frames_done`` frames a resumed run has done
    (the reader's grouping and skip list, and the tactile reference images, come out as in
    the first run), restore the particles and the generator, then step the filter and
    checkpoint each further frame."""
    done = restored.frames_done
    if restored.particles is not None:
        estimator.particles = restored.particles
    if restored.rng_state is not None:
        estimator.rng.bit_generator.state = restored.rng_state  # the filter's generator too (one object)
    if done:  # the state the last completed frame carried over, kept in its journal record
        estimator.restore_consistency(ck.results()[done - 1].consistency)
    if progress is not None:  # at once, from the resumed frame (0 for a fresh run)
        progress(min(done, total), total)
    primed: set[str] = set()
    n = 0
    for frame in reader:
        if n < done:
            _prime_observer(estimator, frame, primed)
        else:
            result = estimator.step(frame)
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
    counts = [log.summary().topic(s.image_topic).message_count for s in sensors if log.summary().has_topic(s.image_topic)]
    n = max(counts) if counts else 0
    return min(n, max_frames) if max_frames else n


def _summary(results: list[FrameEstimate], cfg: Config, log_path: Path, elapsed: float, skipped,
             run_warnings: list[dict] | tuple = ()) -> dict:
    """The run's summary.json. ``run_warnings``: warnings not tied to a frame (meshes, units),
    reported with the frames' failure-mode warnings under ``warnings`` (counted per kind in
    ``warning_counts``); ``sensors`` gives each sensor's agreement with the estimate and
    weight factor (see filter/health.py)."""
    last = results[-1]
    q = se3.to_quat_xyzw(last.T_world_object)
    qe = se3.to_quat_xyzw(last.T_ee_object)
    flags: dict[str, int] = {}
    warnings = list(run_warnings)
    agreement = []
    for r in results:
        for fl in r.flags:
            flags[fl] = flags.get(fl, 0) + 1
        warnings.extend(r.warnings)
        agreement.append((r.index, getattr(r, "sensor_iou", {})))
    out = {
        "log": str(log_path),
        "object": cfg.object.name,
        "modalities": list(cfg.modalities),
        "masking": {"camera": cfg.masking.camera.backend, "tactile": cfg.masking.tactile.backend},
        "particles": cfg.filter.num_particles,
        "seed": cfg.filter.seed,
        "frames_processed": len(results),
        "frames_skipped": len(skipped),
        "run_time_s": round(elapsed, 3),
        "time_per_frame_s": round(elapsed / len(results), 4),
        "final": {
            "stamp_ns": last.stamp_ns,
            "T_world_object": {"translation_m": last.T_world_object[:3, 3].tolist(), "quaternion_xyzw": q.tolist()},
            "T_ee_object": {"translation_m": last.T_ee_object[:3, 3].tolist(), "quaternion_xyzw": qe.tolist()},
            "covariance_ee": last.covariance.tolist(),
            "translation_std_m": float(np.sqrt(np.trace(last.covariance[:3, :3]) / 3)),
            "rotation_std_deg": float(np.degrees(np.sqrt(np.trace(last.covariance[3:, 3:]) / 3))),
            "ess": last.ess,
        },
        "flags": flags,
        "warnings": warnings,
        "warning_counts": count_warnings(warnings),
        "sensors": sensor_report(agreement, warnings),
    }
    if last.T_world_object_gt is not None:
        dt = last.T_world_object[:3, 3] - last.T_world_object_gt[:3, 3]
        out["final"]["ground_truth_translation_error_mm"] = float(1000 * np.linalg.norm(dt))
        out["final"]["ground_truth_rotation_error_deg"] = float(
            np.degrees(se3.rotation_angle(last.T_world_object[:3, :3], last.T_world_object_gt[:3, :3]))
        )
    return out


def warning_report(summary: dict) -> list[str]:
    """The summary's warnings for the terminal: one line per kind, saying in how many frames."""
    return warning_lines(summary.get("warnings", []), summary["frames_processed"])


def write_track(out_dir: Path, results: list[FrameEstimate], cfg: Config, summary: dict) -> None:
    """track.mcap, track.csv, summary.json and config.resolved.yaml, each written atomically."""
    with LogWriter(out_dir / "track.mcap") as w:
        write_track_scene(w, [r.stamp_ns for r in results], np.stack([r.T_world_object for r in results]),
                          np.stack([r.T_ee_object for r in results]),
                          object_triangles(cfg.object.mesh, cfg.object.units), cfg.frames.world, cfg.frames.ee)
        for r in results:
            w.write_pose("/mvtop/object_pose", r.T_world_object, r.stamp_ns, cfg.frames.world)
            w.write_pose("/mvtop/object_pose_ee", r.T_ee_object, r.stamp_ns, cfg.frames.ee)
            w.write_pose_array("/mvtop/particles", r.particles_world, r.stamp_ns, cfg.frames.world)
    lines = ["frame,stamp_ns,x_m,y_m,z_m,qx,qy,qz,qw,ee_x_m,ee_y_m,ee_z_m,ee_qx,ee_qy,ee_qz,ee_qw,"
             "std_translation_m,std_rotation_deg,ess,contact,mask_mode,flags"]
    for r in results:
        q = se3.to_quat_xyzw(r.T_world_object)
        qe = se3.to_quat_xyzw(r.T_ee_object)
        st = np.sqrt(np.trace(r.covariance[:3, :3]) / 3)
        sr = np.degrees(np.sqrt(np.trace(r.covariance[3:, 3:]) / 3))
        vals = [*r.T_world_object[:3, 3], *q, *r.T_ee_object[:3, 3], *qe]
        contact = "" if r.contact is None else str(int(r.contact))
        lines.append(",".join([str(r.index), str(r.stamp_ns)] + [f"{v:.9f}" for v in vals]
                              + [f"{st:.9f}", f"{sr:.6f}", f"{r.ess:.2f}", contact, r.mask_mode, "|".join(r.flags)]))
    with atomic_output(out_dir / "track.csv", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    with atomic_output(out_dir / "config.resolved.yaml", "w") as fh:
        fh.write(dump_config(cfg))
