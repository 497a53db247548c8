"""The M-VTOP estimator's per-frame step: frames in, estimates out (no io).

Per frame (paper section IV): the observation (``observation``: ROIs and observed masks,
Algorithm 1-2 for the cameras), the frame's likelihood (``likelihood``: eq. 1-2 and 8-9),
then the particle filter (``filter.pf``, Algorithm 3): the motion model (``motion``,
Algorithm 4), the tempered refinement within the frame, the weighted-mean estimate; and the
failure checks of ``filter.health`` (ESS collapse, estimate jumps, sensors that disagree).

Searches (``filter.search``). The first frame starts from one cross-entropy search of the grasp
prior (the checks below catch the wrong modes a second one was for: README, *One search on the
first frame*); every later frame checks with a short local search whether the belief sits at
the likelihood's peak. When a searched
pose beats both the estimate and the best particle by ``search.recheck_margin`` nats, the
frame is redone from the searched poses and kept if its estimate fits better. A sensor that
disagrees with the estimate the others agree on adds the dissent search's poses to that check
(``search.dissent``): the poses it explains, before the consistency watch scales it down.
Every ``search.rival_every`` frames a fresh search of the prior, with a generator of its own,
looks for another pose that explains the frame about as well as the estimate (a rival mode):
it changes no estimate, only the reported covariance and the warnings (with
``search.check_at_contact`` also on the first frame of each contact). With touch and camera
proposals, the mode check (``search.mode_check``) takes its place: it searches the prior with
every pose choosing its own camera masks among the belief-free proposals
(``likelihood.ProposalLikelihood``), since the frame's masks were chosen by the belief, so a
belief in a wrong mode explains them best; when a far pose beats the estimate by
``search.mode_margin`` on equal terms, the frame is redone from the searched poses, with masks
they choose, and a far pose it cannot tell from the estimate stands as a rival until a later
mode check, searching around it, rules it out (``_rules_out``). In free air the grasp holds, so the
switch must also clear the margin over the frames since the last contact, scored the same way
(``search.mode_history_frames``): one frame whose proposals take in something beside the part
cannot move a belief the frames before it agree on.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from ..config import Config
from ..filter.health import RivalMode, SensorConsistency, is_suspect, jump_warning, left_open, step_warnings, warning
from ..filter.particles import ParticleSet
from ..filter.pf import ParticleFilter
from ..filter.result import StepResult
from ..filter.search import cross_entropy_search, local_search, tempered_resample
from ..geometry import se3
from ..records import Frame
from .evidence import EvidenceReport, evidence_covariance, leave_one_out, likelihood_widths, profile_widths
from .extrinsics import CameraAlignment, check_camera, corrected_frame
from .likelihood import Likelihood, ProposalLikelihood
from .motion import MotionModel
from .observation import Observation, ObservationModel
from .prior import GraspPriorModel
from .scene import SceneModel
from .symmetry import SymmetryFold

_RIVAL_STREAM = 0x52495641  # seeds the rival checks' generators apart from the filter's
_MODE_STREAM = 0x4D4F4445  # and the mode checks'
_PROFILE_STREAM = 0x50524F46  # and the evidence profiles'


@dataclass
class FrameEstimate:
    """The estimator's output for one frame.

    ``T_ee_object`` / ``T_world_object`` the estimate (weighted SE(3) mean), ``covariance``
    (6, 6) of x, y, z [m], rx, ry, rz [rad] about the mean in ee axes, ``ess`` the effective
    sample size, ``sensors`` the sensors that scored, ``flags`` the failure modes raised and
    ``warnings`` their records (``filter.health.warning``), ``mask_mode`` how the camera masks
    were made, ``particles_world`` the particles kept for the track (``output.track_particles``).
    """

    index: int
    stamp_ns: int
    T_ee_object: np.ndarray
    T_world_object: np.ndarray
    covariance: np.ndarray
    ess: float
    contact: bool | None
    sensors: tuple[str, ...]
    flags: tuple[str, ...]
    mask_mode: str
    particles_world: np.ndarray = field(repr=False)
    T_world_object_gt: np.ndarray | None = None
    warnings: tuple[dict, ...] = ()
    # per sensor: IoU of its observed mask with the mask rendered at the estimate
    sensor_iou: dict[str, float] = field(default_factory=dict)
    # how well the evidence pins the estimate (``evidence.EvidenceReport``); None when nothing was observed
    evidence: EvidenceReport | None = None
    # the state carried to the next frame (``Estimator.resume_after`` on resume): the sensor consistency
    # watch, and the frames so far that left some pose axis or a rival mode open, of those with evidence
    consistency: dict = field(default_factory=dict)
    unpinned: tuple[int, int] = (0, 0)
    # the rival mode the checks found and none has ruled out yet (None: no rival, or no check yet;
    # ``search.rival_every``; the mode check's, where it searches)
    rival: RivalMode | None = None
    # the first frame's leave-one-out check found the sensors contradicting each other
    # (``search.disagreement_margin``); it stands for the run
    disagreement: RivalMode | None = None
    # on the frame the leave-one-out check read: per sensor, the nats by which the others prefer a pose
    # elsewhere to the estimate without it (None: not judged, fewer than consistency.min_others others)
    leave_one_out: dict[str, float | None] | None = None
    # the latest check's profile widths (6,) (``output.evidence_profile``; None: none measured yet), which
    # the reported covariance uses until the next check, whether or not this frame had evidence
    profile_sigma: np.ndarray | None = None
    # per camera checked so far, what the extrinsics check found (``extrinsics``; None: nothing to judge by), for
    # the run: a corrected camera is used turned from then on, a misaligned one left as recorded makes the run suspect
    extrinsics: dict[str, CameraAlignment | None] = field(default_factory=dict)
    # wall seconds per stage of this frame, which add up to the step (masking, the filter's searches,
    # prediction and refinement, the mode and rival checks, diagnostics), and the likelihood's counts
    # (``Estimator.step``; ``pipelines.track.stage_timing``)
    timings: dict = field(default_factory=dict)
    # per observed sensor, its observed mask and the mask rendered at the estimate, when the caller
    # keeps them (``mvtop estimate --debug-images``: ``pipelines.debug_images.frame_masks``)
    debug_masks: tuple = field(default=(), repr=False)


@dataclass(frozen=True)
class ModeSwitch:
    """What the mode check (``Estimator._mode_check``) did to a frame: its ``record``, a
    ``mode_switch`` warning with the redone frame's new filter ``result`` and the
    ``likelihood`` and ``observation`` of the masks chosen by the searched poses; or, with
    those None and the searched pose as a ``rival`` (it stands as a rival mode, the covariance
    the grasp prior's spread, until a later mode check rules it out), a ``mode_held`` warning
    (the earlier frames held the switch back: the frame and the frames before disagree) or a
    ``rival_mode`` warning (the pose scores too close to the estimate to switch on or to rule
    out)."""

    record: dict
    result: StepResult | None = None
    likelihood: Likelihood | None = None
    observation: Observation | None = None
    rival: RivalMode | None = None


class Estimator:
    """The M-VTOP filter over a stream of frames: the online API, and what ``mvtop
    estimate`` runs over a log.

    cfg, scene : the validated config and the scene built from it (``SceneModel``; or use
      ``Estimator.from_config``).
    frame_pose : ``(tf_frame, stamp_ns) -> T_world_frame`` (4, 4), for environment meshes
      mounted on moving TF frames (fingers); only called when the config has such meshes
      (None: the config must have none).

    ``step(frame)`` takes one ``records.Frame`` (images with their sensor poses, the end
    effector pose, the contact state) and returns its ``FrameEstimate``: the estimate, its
    covariance and the diagnostics ``track.csv`` holds.
    """

    def __init__(self, cfg: Config, scene: SceneModel, frame_pose: Callable[[str, int], np.ndarray] | None = None):
        self.cfg = cfg
        self.scene = scene
        f, s = cfg.filter, cfg.search
        self.rng = np.random.default_rng(f.seed)
        # a symmetric part's belief summarised modulo its symmetries (estimator/symmetry.py)
        self.fold = SymmetryFold.from_config(cfg, scene.symmetries)
        self.motion = MotionModel(
            f.sigma_low_translation_m, np.radians(f.sigma_low_rotation_deg),
            f.sigma_high_translation_m, np.radians(f.sigma_high_rotation_deg), f.translation_axis_scale,
        )
        self.pf = ParticleFilter(
            self.motion, f.resampling, f.ess_threshold, self.rng, ess_collapse_fraction=f.ess_collapse_fraction,
            jump_sigmas=f.jump_sigmas, refine_iterations=f.refine_iterations, refine_shrink=f.refine_shrink,
            floor_translation_m=f.floor_translation_m, floor_rotation_rad=np.radians(f.floor_rotation_deg),
            refine_target_ess_fraction=f.refine_target_ess_fraction,
            collapse_retry_iterations=f.collapse_retry_iterations, posterior_sweeps=f.posterior_sweeps, fold=self.fold,
        )
        self.prior = GraspPriorModel(cfg.grasp_prior, s.bound)
        self.observations = ObservationModel(cfg, scene, frame_pose or _no_moving_frames)
        # per-sensor agreement with the others; scales eq. 1-2 weights of a sensor that keeps disagreeing
        self.consistency = SensorConsistency(**vars(cfg.consistency))
        self.search = {"rounds": s.rounds, "elite_fraction": s.elite_fraction, "widen": s.widen,
                       "floor_translation_m": s.floor_translation_m,
                       "floor_rotation_rad": np.radians(s.floor_rotation_deg)}
        self.particles: ParticleSet | None = None
        self.last_likelihood: Likelihood | None = None
        self._search_s = 0.0  # search time of the current frame
        self.use_contact = "contact" in cfg.modalities
        self.unpinned = (0, 0)  # frames whose evidence left some pose axis open, frames with evidence
        self.rival: RivalMode | None = None  # the rival no check has ruled out yet
        self.disagreement: RivalMode | None = None  # the first frame's sensors contradicted each other
        self.profile_sigma: np.ndarray | None = None  # the latest check's profile widths (output.evidence_profile)
        self.extrinsics: dict[str, CameraAlignment | None] = {}  # per camera checked, the extrinsics check's finding
        self.in_contact = False  # the last frame's contact state (search.check_at_contact)
        self.settled = False  # whether the last frame left a settled belief (filter.tracking_particles)
        # the frames since the last contact, for the mode check (search.mode_history_frames; none kept
        # where the check never runs)
        checks = s.mode_check and "vision" in cfg.modalities and "tactile" in cfg.modalities
        self.history: deque[Frame] = deque(maxlen=s.mode_history_frames if checks else 0)

    @classmethod
    def from_config(cls, cfg: Config, frame_pose: Callable[[str, int], np.ndarray] | None = None) -> Estimator:
        """The online estimator of a validated config (``config.load_config``): loads the
        meshes it names and, with the contact modality, builds the contact grid (a second or
        two). Feed it frames with ``step``; ``frame_pose`` as for the constructor."""
        return cls(cfg, SceneModel(cfg, build_contact="contact" in cfg.modalities), frame_pose)

    @property
    def observer(self):
        """The masking backends (``observation.Observer``)."""
        return self.observations.observer

    # --- one frame -------------------------------------------------------------------------

    def step(self, frame: Frame) -> FrameEstimate:
        """One frame: observation, likelihood, filter update, and the failure checks of
        ``filter.health``; the estimate is checked against the previous frame's belief and
        the motion model (``estimate_jump``)."""
        t_step = time.perf_counter()
        self._search_s = 0.0
        frame, aligned = self._aligned(frame)
        align_s = time.perf_counter() - t_step
        first = self.particles is None
        if first:
            self.particles = self.prior.sample(self.cfg.filter.num_particles, self.rng)
        ps = self.particles
        # the log's contact signal c_k moves the particles (Algorithm 3-4) in every method; it is
        # evidence (eq. 8-9) only with the contact modality
        contact = self._evidence_contact(frame)
        due = self._check_due(frame.index, onset=bool(frame.contact) and not first and not self.in_contact)
        same_contact = bool(frame.contact) == self.in_contact
        self.in_contact = bool(frame.contact)
        observation = self.observations.observe(frame, ps, self._converged(ps, first))
        t_masks = time.perf_counter()
        likelihood = Likelihood(self.cfg, self.scene, frame, observation, contact, self.consistency.weight_factor)
        has_evidence = bool(observation.sensors) or bool(contact)
        f = self.cfg.filter
        tracking = (f.tracking_particles > 0 and f.refine_iterations > 0 and has_evidence and not first and not due
                    and self.settled and same_contact)
        if first and self.cfg.search.disagreement_margin is not None:
            likelihood.record()  # the first frame's searched poses, for the leave-one-out check
        result = self._assimilate(ps, first, bool(frame.contact), has_evidence, likelihood, tracking)
        taped = likelihood.stop()
        t_filter, search_s = time.perf_counter(), self._search_s
        checked = (self.cfg.search.mode_check and due and bool(observation.cameras)
                   and bool(observation.tactile))
        switch, mode_ruled_out = self._mode_check(frame, result, likelihood, contact) if checked else (None, None)
        switched = switch is not None and switch.result is not None
        if switched:
            result, likelihood, observation = switch.result, switch.likelihood, switch.observation
        self.last_likelihood = likelihood  # for diagnostics: the frame's likelihood at any pose, e.g. the truth's
        checks_s = time.perf_counter() - t_filter  # the mode check's searches and refinements; the rival check's below
        counts = {"invalid_log_likelihood": likelihood.invalid, "evaluated_poses": likelihood.evaluated}
        warnings = step_warnings(frame.index, {**result.diagnostics, **counts}, len(result.particles))
        flags = list(result.flags)
        warnings += [a.warning() for a in aligned]
        if switch is not None:
            warnings.append(switch.record)
        if switched:
            flags.append("mode_switch")

        # a sensor that keeps disagreeing with all the others gets its weight scaled down from
        # the next frame on; if its pull had biased the belief, the other sensors draw it back
        # through the filter and the re-search check (restarting from the grasp prior at that
        # frame was no better on logs with one pad's image flipped: conn1 3.9 deg against 1.5
        # deg this way after 14 frames, conn2 2.5 against 3.7)
        sensor_iou = likelihood.sensor_ious(result.estimate)
        for name, iou, others in self.consistency.observe(sensor_iou, likelihood.informative(sensor_iou)):
            what = "tactile sensor" if name in observation.tactile else "camera"
            warnings.append(warning(
                frame.index, "sensor_downweighted",
                f"{what} {name!r} disagreed with the other sensors for {self.consistency.frames} frames in a row "
                f"(IoU of its mask at the estimate {iou:.2f}, the others' median {others:.2f}): its weight is "
                f"scaled by {self.consistency.factor:g} from frame {frame.index + 1} on",
                sensor=name, iou_at_estimate=iou, others_median_iou=others, weight_factor=self.consistency.factor,
            ))
            flags.append("sensor_downweighted")
        flags = list(dict.fromkeys(flags))
        evidence = self._evidence(likelihood, result.estimate, sensor_iou, has_evidence)
        if evidence is not None and due and self._profiled(observation):
            t_profile = time.perf_counter()
            self.profile_sigma = self._profile(frame.index, likelihood, result.estimate, evidence.log_likelihood)
            checks_s += time.perf_counter() - t_profile
        elif evidence is not None and due:
            self.profile_sigma = None  # a check frame the cameras see again: the probe's widths hold
        if evidence is not None and self.profile_sigma is not None:
            evidence = replace(evidence, profile_sigma=self.profile_sigma)

        if not first:
            jump = self.pf.check_jump(ps.spread(self.fold), result.estimate, bool(frame.contact))
            if jump.jumped:
                cause = ("the frame was redone in another mode" if "mode_switch" in flags
                         else "the belief was re-searched" if "re_searched" in flags else "")
                warnings.append(jump_warning(frame.index, jump, self.pf.jump_sigmas, cause))
                flags.append("estimate_jump")

        # where the mode check searched, it alone judges rivals (search.rival_beside_mode_check)
        judged = mode_ruled_out is not None and not self.cfg.search.rival_beside_mode_check
        if due and evidence is not None and not judged:
            t_rival = time.perf_counter()
            rival, ruled_out = self._rival_check(frame.index, likelihood, result.estimate)
            checks_s += time.perf_counter() - t_rival
            if rival is not None:
                warnings.append(rival.warning())
            if rival is not None or ruled_out:
                self.rival = rival
        if switch is not None and switch.rival is not None:
            self.rival = switch.rival
        elif judged and mode_ruled_out:
            self.rival = None
        if evidence is not None:
            self.unpinned = (self.unpinned[0] + left_open(evidence.pinned, self.rival), self.unpinned[1] + 1)
        suspect = is_suspect(*self.unpinned, self.cfg.output.suspect_unpinned_fraction)
        if suspect:
            flags.append("suspect_estimate")
        left_out = None
        if taped is not None and has_evidence:
            t_loo = time.perf_counter()
            self.disagreement, left_out = self._disagreement(frame.index, likelihood, result.estimate, taped)
            checks_s += time.perf_counter() - t_loo
            if self.disagreement is not None:
                warnings.append(self.disagreement.warning())
        if self.rival is not None:
            flags.append("rival_mode")
            suspect = True
        if self.disagreement is not None:
            # for the run: the later frames' camera masks follow the belief, and on conn1 1086 of the
            # hard scene the belief-free proposals too ceased to favour the others' pose by frame 29
            # (search.disagreement_margin), while the estimate stayed 4.4 mm off
            flags.append(self.disagreement.kind)
            suspect = True
        misaligned = [a for a in self.extrinsics.values() if a is not None and a.misaligned]
        if misaligned:
            flags.append("camera_extrinsics")
            # a camera left turned (extrinsics.mode: warn, a turn at the searched range's edge, or meshes that do not
            # agree on one turn) pulls the estimate
            suspect = suspect or any(a.suspect for a in misaligned)

        self.settled = not _UNSETTLED.intersection(flags)
        self.particles = result.particles
        est = result.estimate
        covariance = result.spread.covariance
        if self.cfg.output.covariance == "particles_and_evidence":
            if suspect:
                # once the evidence has left some axis open too often, or another pose explains it about
                # as well (a mode the sensors cannot rule out), the truth may be anywhere the grasp prior
                # allows: its spread about the estimate, the estimate's offset from the nominal grasp too
                covariance = covariance + self.prior.covariance_about(est, self.fold)
            elif evidence is not None:
                # the particles can collapse further than the evidence supports (tempering, resampling):
                # the reported covariance adds what the likelihood itself leaves open about the estimate
                covariance = covariance + evidence_covariance(evidence.widths, self.prior.sigma,
                                                              self.cfg.output.evidence_width_factor)
        self.remember(frame)
        n = len(result.particles.poses)
        keep = self.rng.choice(n, size=min(self.cfg.output.track_particles, n), replace=False)
        keep.sort()
        t_end = time.perf_counter()
        return FrameEstimate(
            index=frame.index, stamp_ns=frame.stamp_ns, T_ee_object=est, T_world_object=frame.T_world_ee @ est,
            covariance=covariance, ess=float(result.ess), contact=frame.contact,
            sensors=tuple(observation.sensors), flags=tuple(flags), mask_mode=observation.mask_mode,
            particles_world=frame.T_world_ee @ result.particles.poses[keep], T_world_object_gt=frame.T_world_object_gt,
            warnings=tuple(warnings), sensor_iou=sensor_iou, evidence=evidence,
            consistency={"factors": dict(self.consistency.factors), "streak": dict(self.consistency.streak)},
            unpinned=self.unpinned, rival=self.rival, disagreement=self.disagreement, leave_one_out=left_out,
            profile_sigma=self.profile_sigma, extrinsics=dict(self.extrinsics),
            timings={"masking_s": t_masks - t_step - align_s, "search_s": search_s,
                     "filter_s": t_filter - t_masks - search_s, "checks_s": checks_s + align_s,
                     "diagnostics_s": t_end - t_filter - checks_s,
                     "likelihood_s": likelihood.seconds, "likelihood_calls": likelihood.calls,
                     "poses_scored": likelihood.evaluated, "step_s": t_end - t_step, "tracked": tracking},
        )

    def resume_after(self, last: FrameEstimate) -> None:
        """Continue after frame ``last`` with the state it carried over: the sensor consistency
        watch (``FrameEstimate.consistency``: a resumed run scales the same sensors down at the
        same frames), the count of frames that left an axis or a rival open (``FrameEstimate.unpinned``),
        the rival no check has ruled out yet (``FrameEstimate.rival``), the first frame's
        disagreement (``FrameEstimate.disagreement``), the latest profile widths
        (``FrameEstimate.profile_sigma``), the extrinsics check's findings (``FrameEstimate.extrinsics``),
        the contact state (``search.check_at_contact``) and whether
        it left the belief settled (``filter.tracking_particles``)."""
        self.consistency.factors = dict(last.consistency.get("factors", {}))
        self.consistency.streak = dict(last.consistency.get("streak", {}))
        self.unpinned = tuple(last.unpinned)
        self.rival = last.rival
        self.disagreement = last.disagreement
        self.profile_sigma = last.profile_sigma
        self.extrinsics = dict(last.extrinsics)
        self.in_contact = bool(last.contact)
        self.settled = not _UNSETTLED.intersection(last.flags)

    def remember(self, frame: Frame) -> None:
        """Keep ``frame`` as one of the mode check's earlier frames (``search.mode_history_frames``,
        the latest ones): a frame out of contact joins them; a frame in contact, or of a log
        without a contact signal, empties them (the part may have slipped in the grasp). ``step``
        calls it after each frame; a resumed run calls it on the frames it replays."""
        if frame.contact is False:
            self.history.append(frame)
        else:
            self.history.clear()

    def _aligned(self, frame: Frame) -> tuple[Frame, list[CameraAlignment]]:
        """``frame`` with the cameras the extrinsics check corrected turned (``extrinsics.mode``), and
        the misaligned cameras it found on this frame: each camera is checked on its first image
        (``estimator/extrinsics.py``), and what it found stands for the run."""
        settings = self.cfg.extrinsics
        found = []
        if settings.mode != "off":
            for name, img in frame.cameras.items():
                if name in self.extrinsics:
                    continue
                alignment = check_camera(self.scene, name, img, frame.index,
                                         lambda tf_frame, img=img: self.observations.frame_pose(tf_frame, img.stamp_ns),
                                         settings)
                self.extrinsics[name] = alignment
                if alignment is not None and alignment.misaligned:
                    found.append(alignment)
        return corrected_frame(frame, self.extrinsics), found

    def _evidence_contact(self, frame: Frame) -> bool | None:
        """The frame's contact state as evidence for the contact likelihood (eq. 8-9): the log's
        signal with the contact modality, else None (no contact term)."""
        return frame.contact if self.use_contact else None

    def _check_due(self, index: int, onset: bool) -> bool:
        """Whether frame ``index`` has the rival and mode checks: every ``search.rival_every``
        frames, and with ``search.check_at_contact`` on a contact ``onset`` (a frame in contact
        after one without, not the first frame)."""
        s = self.cfg.search
        return (bool(s.rival_every) and (index + 1) % s.rival_every == 0) or (s.check_at_contact and onset)

    def _evidence(self, likelihood: Likelihood, T_ee_object: np.ndarray, sensor_iou: dict[str, float],
                  observed: bool) -> EvidenceReport | None:
        """The frame's evidence diagnostic at the estimate (``evidence``), None without evidence."""
        if not observed:
            return None
        o = self.cfg.output
        ll, sigma = likelihood_widths(likelihood, T_ee_object, o.evidence_step_translation_m,
                                      np.radians(o.evidence_step_rotation_deg))
        return EvidenceReport(dict(sensor_iou), ll, sigma)

    def _profiled(self, observation: Observation) -> bool:
        """Whether a check frame with this observation measures the profile widths
        (``output.evidence_profile``; ``without_cameras``: when no camera's evidence enters it)."""
        mode = self.cfg.output.evidence_profile
        return not observation.cameras if mode == "without_cameras" else mode

    def _profile(self, index: int, likelihood: Likelihood, T_ee_object: np.ndarray, centre_ll: float) -> np.ndarray:
        """Frame ``index``'s profile widths (6,) about the estimate (``evidence.profile_widths``) on
        the likelihood bounded by the grasp prior, from a generator of its own (seeded by
        ``filter.seed`` and the frame index: the filter's draws, and so the estimates, are the
        same with or without it); the search's spread is ``output.evidence_profile_scale`` probe
        steps."""
        o = self.cfg.output
        rng = np.random.default_rng([self.cfg.filter.seed, index, _PROFILE_STREAM])
        return profile_widths(
            self.prior.bounded(likelihood), T_ee_object, centre_ll, o.evidence_profile_translation_m,
            np.radians(o.evidence_profile_rotation_deg), o.evidence_profile_scale * o.evidence_step_translation_m,
            np.radians(o.evidence_profile_scale * o.evidence_step_rotation_deg), rng, o.evidence_profile_population,
            o.evidence_profile_rounds, self.cfg.search.elite_fraction)

    # --- the filter update -----------------------------------------------------------------

    def _converged(self, belief: ParticleSet, first: bool) -> bool:
        """Whether the cameras switch to the promptable mode (``masking.prompt_when_converged``):
        after the first frame, once the belief's RMS spread is below the configured bounds."""
        m = self.cfg.masking
        if first or not m.prompt_when_converged:
            return False
        spread = belief.spread(self.fold)
        return (spread.translation_rms_m < m.converged_translation_m
                and spread.rotation_rms_rad < np.radians(m.converged_rotation_deg))

    def _assimilate(self, ps: ParticleSet, first: bool, in_contact: bool, has_evidence: bool,
                    likelihood: Likelihood, tracking: bool = False) -> StepResult:
        """The frame's filter update: a plain prediction when the frame holds no evidence
        (no sensor observed, no contact term); else the prediction (the first frame: a global
        search of the grasp prior) and the observation (``ParticleFilter.assimilate``), then,
        with the refinement, the re-search check (``_recheck``). ``in_contact``: the log's
        contact signal, for the motion model (Algorithm 4). The refinement returns
        ``filter.tracking_particles`` particles on a frame ``step`` found ``tracking``, else
        ``filter.num_particles``; the first frame's global search and a frame without evidence
        keep the count they have."""
        if not has_evidence:
            return self.pf.assimilate(self.pf.predict(ps, in_contact), lambda T: np.zeros(len(T)), 0)
        bounded = self.prior.bounded(likelihood)
        iterations = self.cfg.filter.refine_iterations * (self.cfg.search.first_frame_iteration_factor if first else 1)
        predicted = self._global_search(bounded) if first else self.pf.predict(ps, in_contact)
        n_out = (self.cfg.filter.tracking_particles if tracking
                 else None if iterations == 0 else self.cfg.filter.num_particles)
        result = self.pf.assimilate(predicted, likelihood, iterations, n_out)
        return self._recheck(result, first, likelihood, bounded) if iterations > 0 else result

    def _global_search(self, bounded: Callable[[np.ndarray], np.ndarray]) -> ParticleSet:
        """Coarse search of the grasp prior on the first frame (Algorithm 1's pose
        candidates): ``search.init_factor`` times more prior samples than particles moved
        towards the likelihood's basin by a cross-entropy search, then N of them by tempered
        resampling. The frame's refinement then starts from the basin of the likelihood
        instead of from the whole prior, which a few hundred particles cannot cover at
        sub-millimetre scale."""
        n = self.cfg.filter.num_particles
        poses, ll = self._prior_search(bounded, rounds=self.cfg.search.first_frame_rounds)
        if not np.isfinite(ll).any():
            return self.prior.sample(n, self.rng)
        return tempered_resample(poses, ll, n, self.cfg.filter.resampling, self.rng)

    def _prior_search(self, bounded: Callable[[np.ndarray], np.ndarray], rng: np.random.Generator | None = None,
                      init_factor: int | None = None, rounds: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One cross-entropy search from fresh grasp-prior samples: poses and log-likelihoods
        (drawn from ``rng``, by default the filter's generator; ``init_factor`` samples per
        particle for ``rounds`` rounds, by default ``search.init_factor`` and the rival check's
        ``search.rounds``; the first frame's search passes ``search.first_frame_rounds``)."""
        t0 = time.perf_counter()
        rng = self.rng if rng is None else rng
        s = self.cfg.search
        factor = s.init_factor if init_factor is None else init_factor
        start = self.prior.sample(self.cfg.filter.num_particles * factor, rng).poses
        budget = {**self.search, "rounds": s.rounds if rounds is None else rounds}
        out = cross_entropy_search(start, bounded, rng, **budget)
        self._search_s += time.perf_counter() - t0
        return out

    def _rival_check(self, index: int, likelihood: Likelihood,
                     T_ee_object: np.ndarray) -> tuple[RivalMode | None, bool]:
        """A fresh search of the grasp prior on frame ``index``'s likelihood, from a generator of
        its own (seeded by ``filter.seed`` and the frame index: the filter's draws, and so the
        estimates, are the same with or without it). Its best pose is a rival when it lies farther
        from the estimate ``T_ee_object`` (4, 4) than ``search.rival_translation_m`` or
        ``rival_rotation_deg`` (after the part's symmetries) and scores at most ``rival_margin``
        nats below it: the sensors do not tell the two apart. Returns the rival (or None) and
        whether an earlier rival is ruled out: the search's best pose is the estimate's own mode
        (within those distances) and a search around the earlier rival, carried to where the
        estimate now is, finds nothing within the margin either (``_rules_out``: a fresh search
        that does not find a mode again has not shown it gone); a best pose far away but scoring
        lower rules nothing out, so an earlier rival stands. Measured on simulated grasps: touch
        alone leaves such rivals on the cube, plug and conn1 (1-5 mm away within a few nats),
        cameras and touch together none within 20 nats (README)."""
        s = self.cfg.search
        bounded = self.prior.bounded(likelihood)
        poses, ll = self._prior_search(bounded, np.random.default_rng([self.cfg.filter.seed, index, _RIVAL_STREAM]))
        if not np.isfinite(ll).any():
            return None, False
        best = poses[int(np.argmax(ll))]
        moved, turned, same = self._distance(best, T_ee_object)
        below = float(bounded(T_ee_object[None])[0] - np.max(ll))
        if same:
            return None, self._rules_out(bounded, likelihood, T_ee_object, True, index)
        rival = RivalMode(index, moved, turned, below, se3.invert(T_ee_object) @ best)
        return (rival if below <= s.rival_margin else None), False

    def _disagreement(self, index: int, likelihood: Likelihood, T_ee_object: np.ndarray,
                      taped: tuple[np.ndarray, np.ndarray, np.ndarray]
                      ) -> tuple[RivalMode | None, dict[str, float | None]]:
        """The leave-one-out check on frame ``index`` (``search.disagreement_margin``): over the
        poses the frame's searches scored (``taped``: poses, per-sensor terms, log-likelihoods)
        within the grasp prior and beyond the rival distances from the estimate ``T_ee_object``
        (4, 4), each sensor is left out in turn (``evidence.leave_one_out``). Where the others
        prefer such a pose to the estimate by the margin, the sensors contradict each other: the
        rival names the sensor whose gain is largest, the one the estimate rests on. Measured on
        a simulated conn1 grasp (hard scene, seed 1086) whose side camera missed the shadowed face:
        without that camera the others preferred a pose 5.2 mm away, the truth's, by 20.4 nats.
        Returns the rival (None: the sensors agree) and the gain per sensor (None where it was not
        judged: fewer than ``consistency.min_others`` other weighted sensors, or no pose elsewhere)
        (README: Sensors that disagree)."""
        poses, terms, ll = taped
        _, _, same = self._distances(poses, T_ee_object)
        ll_est, terms_est = likelihood.scored(T_ee_object[None])
        gains, rows = leave_one_out(terms, ll, self.prior.within(poses) & ~same, terms_est[0], float(ll_est[0]))
        # one sensor against at least consistency.min_others (the consistency watch's rule): one
        # camera left alone is free along its line of sight, and fits coarse masks better elsewhere
        weighted = np.concatenate([likelihood.gamma, likelihood.nu]) > 0
        gains = np.where(weighted.sum() - weighted >= self.cfg.consistency.min_others, gains, -np.inf)
        names = likelihood.observation.sensors
        report = {n: (float(g) if np.isfinite(g) else None) for n, g in zip(names, gains)}
        j = int(np.argmax(gains)) if len(gains) else -1
        if j < 0 or not gains[j] >= self.cfg.search.disagreement_margin:
            return None, report
        best = poses[rows[j]]
        moved, turned, _ = self._distance(best, T_ee_object)
        return RivalMode(index, moved, turned, float(ll_est[0] - ll[rows[j]]), se3.invert(T_ee_object) @ best,
                         sensor=names[j], others_gain=float(gains[j])), report

    def _mode_check(self, frame: Frame, result: StepResult, likelihood: Likelihood,
                    contact: bool | None) -> tuple[ModeSwitch | None, bool | None]:
        """The mode check (``search.mode_check``): a fresh search of the grasp prior
        (``search.mode_init_factor``, ``mode_rounds``), from a generator of its own, with every pose
        choosing its own camera masks among the frame's belief-free proposals
        (``ProposalLikelihood``); only on frames with touch as well as camera proposals. When its
        best pose lies farther from the estimate than ``search.rival_translation_m`` /
        ``rival_rotation_deg`` (after the part's symmetries) and beats it by more than
        ``search.mode_margin`` nats, on this frame alone and on it and the earlier frames
        (``history``, ``_earlier_likelihoods``) together, the frame is redone from the searched
        population: the camera masks chosen again with those poses as the belief, the consistency
        watch's verdicts forgotten (they judged the sensors against the old mode), and the
        refinement run on the new likelihood. The redo is kept when its estimate too beats the old
        one by the margin on equal terms (both ways); otherwise the filter's generator and the watch
        are put back, so a run without a switch has the estimates of a run without the check.
        Returns the redo, the hold (``mode_held``: the earlier frames alone kept the estimate), a
        rival (the best pose scores from ``search.rival_margin`` below the estimate to
        ``mode_margin`` above it: the frame's belief-free evidence cannot tell the two apart), or
        None: the search found the estimate's own mode, or nothing within the rival margin; and
        whether the rival standing from an earlier check is ruled out (``_rules_out``), or the
        frame was redone from the searched poses (None: no search, for want of proposals or of a
        finite score; the rival check judges the frame instead).
        On simulated grasps whose first frame settled in a wrong mode the belief's own masks favour
        it by tens of nats, while on these terms the truth wins by as much (README: Mode check). The
        earlier frames can only hold a switch back: in free air one in-hand pose explains them all,
        and on a closed-loop shaft-peg grasp (1010) hovering 4 mm above its receptacle the camera
        proposals took in the receptacle's mouth below the peg's tip, so a pose 6.6 mm deeper beat
        the truth by 7-10 nats on frames 7-9 alone while frames 0-6 favoured the truth by 8-26 nats
        each. Without touch the check is not run: each pose's free choice among coarse proposals
        then let poses 2-4 mm and 10-20 deg off beat right estimates by 12-25 nats (cameras and
        contact alone, 12 of 19 simulated grasps switched, 8 of them to a worse final pose)."""
        s, f = self.cfg.search, self.cfg.filter
        proposals = self.observations.proposal_sets(frame)
        if not proposals:
            return None, None
        free = ProposalLikelihood(likelihood, proposals)
        bounded = self.prior.bounded(free)
        rng = np.random.default_rng([f.seed, frame.index, _MODE_STREAM])
        poses, ll = self._prior_search(bounded, rng, s.mode_init_factor, s.mode_rounds)
        if not np.isfinite(ll).any():
            return None, None
        at_estimate = float(bounded(result.estimate[None])[0])
        best = poses[int(np.argmax(ll))]
        moved, turned, same = self._distance(best, result.estimate)
        better = float(np.max(ll)) - at_estimate
        if same or better < -s.rival_margin:
            return None, self._rules_out(bounded, likelihood, result.estimate, same, frame.index)
        scored = "with each pose choosing its own camera masks among the image's proposals, "
        T_estimate_best = se3.invert(result.estimate) @ best
        if better <= s.mode_margin:  # too close to switch on, too close to rule out: a rival mode
            rival = RivalMode(frame.index, moved, turned, -better, T_estimate_best)
            return ModeSwitch(rival.warning(scored), rival=rival), False
        found = f"{scored}a pose {moved:.2f} mm / {turned:.2f} deg from the estimate"
        earlier = self._earlier_likelihoods()

        def held(lead: float, before: float) -> ModeSwitch:
            """The ``mode_held`` outcome: the frame's ``lead`` [nats] over the estimate, undone
            by the earlier frames' ``before``."""
            return ModeSwitch(warning(
                frame.index, "mode_held",
                f"{found} explained the frame {lead:.1f} nats better, but over the "
                f"frames before it since the last contact ({len(earlier)}) the estimate leads by {-before:.1f} nats: "
                "the estimate stands; until a later check rules that pose out, the covariance is the grasp prior's "
                "spread", translation_mm=moved, rotation_deg=turned, nats_better=lead,
                earlier_frames=len(earlier), earlier_nats_better=before, ratio=lead),
                rival=RivalMode(frame.index, moved, turned, -lead, T_estimate_best, held=True))

        before = _gain(earlier, best, result.estimate)
        if better + before <= s.mode_margin:
            return held(better, before), False
        t0 = time.perf_counter()
        generator = self.rng.bit_generator.state
        start = tempered_resample(poses, ll, f.num_particles, f.resampling, self.rng)
        observation = self.observations.observe(frame, start, False)
        saved = (dict(self.consistency.factors), dict(self.consistency.streak))
        self.consistency.reset()
        redo_likelihood = Likelihood(self.cfg, self.scene, frame, observation, contact, self.consistency.weight_factor)
        redo = self.pf.refine(start, redo_likelihood, f.refine_iterations * s.first_frame_iteration_factor)
        self._search_s += time.perf_counter() - t0
        gain = float(bounded(redo.estimate[None])[0]) - at_estimate
        before = _gain(earlier, redo.estimate, result.estimate) if gain > s.mode_margin else 0.0
        if gain <= s.mode_margin or gain + before <= s.mode_margin:
            self.consistency.factors, self.consistency.streak = saved
            self.rng.bit_generator.state = generator
            return (held(gain, before) if gain > s.mode_margin else None), False
        redo_likelihood.add_counts(likelihood)
        record = warning(
            frame.index, "mode_switch",
            f"{found} explained the frame {better:.1f} nats better: the frame was redone "
            f"from it ({gain:.1f} nats better than before) and the sensor consistency watch restarted",
            translation_mm=moved, rotation_deg=turned, nats_better=better, ratio=better,
        )
        return ModeSwitch(record, redo, redo_likelihood, observation), True

    def _rules_out(self, free: Callable[[np.ndarray], np.ndarray], likelihood: Likelihood, T_ee_object: np.ndarray,
                   same: bool, index: int) -> bool:
        """Whether a mode or rival check at frame ``index`` that found no rival rules out the one
        standing (``self.rival``): a cross-entropy search (``search.mode_rounds``, a generator of
        its own) around that hypothesis, carried to where the estimate ``T_ee_object`` (4, 4) now
        is (its ``T_estimate_rival``) and spread as the motion model under contact spreads a
        particle over the frames since it was found (``filter.sigma_high_*`` x sqrt(frames)),
        finds no pose still beyond the rival distances within ``search.rival_margin`` nats of the
        estimate. Scored on the frame's ``likelihood``, as the rival check scores, except a
        held-back switch (``RivalMode.held``): the belief-free terms ``free`` put it well ahead,
        and only they can rule it out, since the frame's camera masks are the belief's choice
        (the rival check has none and passes the frame's). On simulated conn1 grasp 1053 (ends
        3.06 mm off) the mode check at contact onset (frame 16) found a pose 3.07 mm away 15 nats
        ahead (the truth); at frame 19 its own search of the prior ended 3 nats below the
        estimate, the carried pose (0.46 mm from the truth) scored 45 nats below, the truth 15
        above, and this search 10.7 above; a global search on the frame's likelihood alone had
        ruled it out. A rival without a pose is ruled out by a search that ends in the estimate's
        own mode (``same``)."""
        rival = self.rival
        if rival is None or rival.T_estimate_rival is None:
            return same
        s, f = self.cfg.search, self.cfg.filter
        terms = free if rival.held else self.prior.bounded(likelihood)
        carried = T_ee_object @ rival.T_estimate_rival
        start = ParticleSet(np.repeat(carried[None], f.num_particles, axis=0), np.zeros(f.num_particles))
        rng = np.random.default_rng([f.seed, index, _MODE_STREAM, _RIVAL_STREAM])
        spread = np.sqrt(max(1, index - rival.frame))
        t0 = time.perf_counter()
        sigma_t, sigma_r = spread * f.sigma_high_translation_m, spread * np.radians(f.sigma_high_rotation_deg)
        poses, ll = local_search(start, terms, rng, sigma_t, sigma_r, **{**self.search, "rounds": s.mode_rounds})
        self._search_s += time.perf_counter() - t0
        apart = ~self._distances(poses, T_ee_object)[2] & np.isfinite(ll)
        at_estimate = float(terms(T_ee_object[None])[0])
        return not apart.any() or at_estimate - float(np.max(ll[apart])) > s.rival_margin

    def _earlier_likelihoods(self) -> list[Callable[[np.ndarray], np.ndarray]]:
        """The mode check's terms on its earlier frames (``history``): per frame, the
        log-likelihood with each pose choosing among the frame's belief-free camera proposals
        (``ProposalLikelihood``), its tactile masks and windows those of the grasp prior's
        fixed poses, so no belief enters; restricted to the search region. Made only when a
        switch is in question, and not kept (the observation and the proposals, which the
        observer makes once per image: about 0.24 s a frame of two cameras on the shaft-peg scene
        of ``tests/estimator/test_dissent.py``, this 2-core machine, busy)."""
        out = []
        prior = ParticleSet(self.observations.prior_poses, np.zeros(len(self.observations.prior_poses)))
        for past in self.history:
            proposals = self.observations.proposal_sets(past)
            if not proposals:
                continue
            observation = self.observations.observe(past, prior, False)
            contact = self._evidence_contact(past)
            likelihood = Likelihood(self.cfg, self.scene, past, observation, contact)
            out.append(self.prior.bounded(ProposalLikelihood(likelihood, proposals)))
        return out

    def _distance(self, T_ee_object: np.ndarray, reference: np.ndarray) -> tuple[float, float, bool]:
        """How far pose ``T_ee_object`` (4, 4) lies from ``reference`` (4, 4) after the part's
        symmetries, [mm] and [deg], and whether that is the same mode: within
        ``search.rival_translation_m`` and ``search.rival_rotation_deg``."""
        moved, turned, same = self._distances(T_ee_object[None], reference)
        return float(moved[0]), float(turned[0]), bool(same[0])

    def _distances(self, T_ee_object: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_distance`` of each of the poses ``T_ee_object`` (N, 4, 4): (N,) each."""
        s = self.cfg.search
        T = T_ee_object if self.fold is None else self.fold(T_ee_object, reference)
        moved = 1000.0 * np.linalg.norm(T[:, :3, 3] - reference[:3, 3], axis=1)
        turned = np.degrees(se3.rotation_angle(T[:, :3, :3], reference[:3, :3]))
        return moved, turned, (moved <= 1000.0 * s.rival_translation_m) & (turned <= s.rival_rotation_deg)

    def _recheck(self, result: StepResult, first: bool, likelihood: Likelihood,
                 bounded: Callable[[np.ndarray], np.ndarray]) -> StepResult:
        """The re-search check: after the first frame, a local search around the belief; on every
        frame, the dissent searches (``_dissent_search``). If a searched pose's log-likelihood
        beats both the estimate and the best particle by ``search.recheck_margin`` nats, the
        belief missed the likelihood's peak (slip faster than the motion model, or a mode a
        dissenting sensor explains): the frame is redone from the searched population and its
        result kept (flag ``re_searched``) if its estimate fits better. The first frame has no
        second search of the grasp prior (README, *One search on the first frame*)."""
        f, s = self.cfg.filter, self.cfg.search
        if first:
            poses, ll = np.empty((0, 4, 4)), np.empty(0)
        else:
            t0 = time.perf_counter()
            poses, ll = local_search(result.particles, bounded, self.rng, s.recheck_sigma_translation_m,
                                     np.radians(s.recheck_sigma_rotation_deg),
                                     **{**self.search, "rounds": s.recheck_rounds})
            self._search_s += time.perf_counter() - t0
        for name in self._dissenting(likelihood, result.estimate):
            d_poses, d_ll = self._dissent_search(name, likelihood, bounded)
            poses, ll = np.concatenate([poses, d_poses]), np.concatenate([ll, d_ll])
        if not np.isfinite(ll).any():
            return result
        best = poses[int(np.argmax(ll))]
        cur = result.particles.poses
        ll_cur = result.log_likelihoods if result.log_likelihoods is not None else likelihood(cur)
        ref = cur[int(np.argmax(ll_cur))]
        cmp = likelihood(np.stack([result.estimate, ref, best]))
        if cmp[2] - max(cmp[0], cmp[1]) <= s.recheck_margin:
            return result
        alt = self.pf.refine(tempered_resample(poses, ll, f.num_particles, f.resampling, self.rng), likelihood,
                             f.refine_iterations * s.first_frame_iteration_factor)
        cmp2 = likelihood(np.stack([result.estimate, alt.estimate]))
        if cmp2[1] > cmp2[0]:
            alt.diagnostics.setdefault("flags", []).append("re_searched")
            return alt
        return result

    def _dissenting(self, likelihood: Likelihood, T_ee_object: np.ndarray) -> list[str]:
        """The full-weight sensors that disagree with the estimate ``T_ee_object`` (4, 4) the
        others agree on (``SensorConsistency.disagreeing``) and have not yet done so for
        ``consistency.frames`` frames: the ones the watch would scale down next."""
        if not self.cfg.search.dissent:
            return []
        ious = likelihood.sensor_ious(T_ee_object)
        verdict = self.consistency.disagreeing(ious, likelihood.informative(ious))
        return [n for n, med in verdict.items() if med is not None and self.consistency.weight_factor(n) == 1.0
                and self.consistency.streak.get(n, 0) < self.consistency.frames]

    def _dissent_search(self, name: str, likelihood: Likelihood,
                        bounded: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The poses a dissenting sensor ``name`` explains, then the best of them for the whole
        frame: a cross-entropy search of the grasp prior's region on that sensor's IoU alone,
        continued for ``search.recheck_rounds`` rounds on the frame's log-likelihood. A sensor
        outvoted by the others is either wrong (a flipped image: no pose explains it, and the
        consistency watch scales it down) or right about a pose the others' evidence misled
        the belief away from (a wrong mode whose basin a joint search misses when the sensor's
        IoU rises only within a fraction of a millimetre of it). Poses (M, 4, 4) and their
        log-likelihoods (M,)."""
        t0 = time.perf_counter()
        start = self.prior.sample(self.cfg.filter.num_particles * self.cfg.search.init_factor, self.rng).poses
        alone = self.prior.bounded(lambda T: likelihood.sensor_iou(name, T))
        poses, _ = cross_entropy_search(start, alone, self.rng, **self.search)
        joint = {**self.search, "rounds": self.cfg.search.recheck_rounds}
        out = cross_entropy_search(poses, bounded, self.rng, **joint)
        self._search_s += time.perf_counter() - t0
        return out


# flags after which the next frame keeps filter.num_particles, never the tracking mode's fewer
_UNSETTLED = frozenset({"degenerate_weights", "ess_collapsed", "tempering_forced", "estimate_jump", "re_searched",
                        "mode_switch", "rival_mode", "sensor_downweighted", "suspect_estimate", "sensors_disagree"})


def _gain(likelihoods: list[Callable[[np.ndarray], np.ndarray]], T_ee_object: np.ndarray,
          reference: np.ndarray) -> float:
    """Nats by which pose ``T_ee_object`` (4, 4) beats ``reference`` (4, 4) over the
    log-likelihoods ``likelihoods`` together (0 without any)."""
    gain = 0.0
    for likelihood in likelihoods:
        ll = likelihood(np.stack([T_ee_object, reference]))
        if ll[0] != ll[1]:  # both outside the search region: no say
            gain += float(ll[0] - ll[1])
    return gain


def _no_moving_frames(frame: str, stamp_ns: int) -> np.ndarray:
    raise ValueError(f"the config has an environment mesh in TF frame {frame!r}: give the Estimator a frame_pose "
                     "callable that returns T_world_frame at a stamp")
