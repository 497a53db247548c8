"""The M-VTOP likelihood of one frame: ``Likelihood`` maps object poses ``T_ee_object
(N, 4, 4)`` to log-likelihoods ``(N,)`` (eq. 6 in log space), the visuo-tactile score of
eq. 1-2 over the frame's observed masks plus the contact log-likelihood of eq. 8-9.

Score. Each sensor's observed mask (``observation.Observation``) is compared with the mask
rendered at the pose, in the sensor's ROI (IoU: ``render.base.score_masks``); eq. 2 sums the
IoUs weighted by ``gamma`` (tactile) and ``nu`` (cameras), and the log-likelihood is that sum
over the temperature ``tau`` of eq. 1. Eq. 1's softmax normalisation over the particles is
left out: it is a constant within one batch, but poses scored in different calls are compared
(Metropolis ratios, search elites), so every call must score on the same scale.

Depth. A tactile mask says where the gel is pressed, not how deep: a part pressed deeper
than the sensor measured, e.g. tilted into one pad about the grasp, renders the same mask.
With ``masking.tactile_depth_tolerance_m`` and a depth topic, the observed contact pixels a
pose presses deeper than the measured indentation plus the tolerance are left out of its
rendered contact, so they count as missed (beyond the paper; ``Likelihood.depth_limit``).

Contact. When the frame reports contact and the scene has a contact model, eq. 9's
``log sigma((tau_c - phi) / sigma_d)`` of the signed distance ``phi`` between the object at
the pose and the fixed environment (eq. 8) is added (``contact.likelihood``), and with it,
beyond the paper, ``log sigma((phi + tau_p) / sigma_p)``: a pose sunk into the environment is
as impossible as one far from it (``contact.penetration_*``).

Contour. With ``edges.gain`` > 0, each camera's evidence that the object's projected contour
at the pose runs along the image's edges, times the gain, is added (beyond the paper:
``estimator/edges.py``); it reads the image alone, at a fraction of a pixel.

Missing sensors. A sensor whose IoU column is NaN for every particle is absent from
this frame (no image, or no usable observed mask). Its importance weight is dropped and
the weights of the sensors present are rescaled to sum to one, as eq. 2 requires
(``sum gamma + sum nu = 1``), so the score keeps the range [0, 1] and the temperature
keeps its meaning whatever the number of sensors. Default weights follow the paper
(``gamma_i = 1/N_T``, ``nu_j = 1/N_V``: modalities weighted equally), with ``N_T`` and
``N_V`` counting the sensors present in the frame; given weights keep their ratios. A
frame without any sensor carries no information: every particle gets ``-log N``.

With ``renormalise=False`` the given weights are used as they are, absent sensors simply
dropped: each sensor then contributes the same ``gamma_i IoU_i / tau`` to the
log-likelihood whichever other sensors are present, as independent sensors' log-likelihoods
add. ``Likelihood`` scores this way, so a frame that holds only tactile images (sensors at
different rates) counts as the tactile part of a full frame rather than as a whole frame
of evidence about what touch alone cannot see.

A NaN for only some particles in a column (IoU undefined for those renders) scores that
term as 0, the worst possible IoU, so such particles are never favoured.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..bitmasks import iou_matrix
from ..config import Config
from ..contact.likelihood import log_contact_likelihood, log_penetration_likelihood
from ..filter.result import valid_log_likelihood
from ..records import Frame
from .observation import Observation
from .scene import OBJECT_ID, SceneModel


def _iou_table(iou: np.ndarray | None, n: int | None, name: str) -> np.ndarray | None:
    if iou is None:
        return None
    a = np.asarray(iou, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"{name} must have shape (N, n_sensors), got {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} rows, expected {n} (one per particle)")
    if np.isinf(a).any():
        raise ValueError(f"{name} contains infinite IoU values")
    return a


def _importance(given: np.ndarray | None, present: np.ndarray, name: str) -> np.ndarray:
    """Per-sensor weights (n_sensors,) before the joint renormalisation; 0 for absent sensors."""
    k = len(present)
    if given is None:
        n_present = int(present.sum())
        return np.where(present, 1.0 / max(n_present, 1), 0.0)
    g = np.asarray(given, dtype=np.float64)
    if g.shape != (k,):
        raise ValueError(f"{name} must have shape ({k},), got {g.shape}")
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise ValueError(f"{name} must be finite and >= 0, got {g}")
    return np.where(present, g, 0.0)


def sensor_weights(
    present_tactile: np.ndarray,
    present_vision: np.ndarray,
    gamma: np.ndarray | None = None,
    nu: np.ndarray | None = None,
    renormalise: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Importance weights ``(gamma (N_T,), nu (N_V,))`` actually used in eq. 2 for one frame.

    present_tactile, present_vision : (N_T,) / (N_V,) bool
      Which sensors have an observation in this frame.
    Absent sensors get 0; the others keep the given ratios (defaults 1/N_T and 1/N_V over
    the present sensors) and, with ``renormalise``, are rescaled to sum to one together
    (without it, given weights are kept as they are). All zeros when no present sensor has
    a positive weight.
    """
    pt = np.asarray(present_tactile, dtype=bool)
    pv = np.asarray(present_vision, dtype=bool)
    g = _importance(gamma, pt, "gamma")
    v = _importance(nu, pv, "nu")
    if not renormalise:
        return g, v
    total = g.sum() + v.sum()
    if total <= 0:
        return np.zeros_like(g), np.zeros_like(v)
    return g / total, v / total


def visuo_tactile_score(
    iou_tactile: np.ndarray | None,
    iou_vision: np.ndarray | None,
    gamma: np.ndarray | None = None,
    nu: np.ndarray | None = None,
    renormalise: bool = True,
) -> np.ndarray:
    """The matching score ``s~_n`` of eq. 2 for every particle, (N,) in [0, 1]: the
    importance-weighted sum of the IoUs.

    iou_tactile, iou_vision : (N, N_T) / (N, N_V) float or None
      IoU between each observed mask and the mask rendered for particle ``n``; a column of
      NaN marks a sensor missing in this frame. None: no sensor of that modality.
    gamma, nu : (N_T,) / (N_V,) float or None
      Sensor importance weights (>= 0); None for the paper's defaults (see the module
      docstring; ``renormalise`` as for ``sensor_weights``).

    Unlike eq. 1's softmax, ``s~ / tau`` does not depend on which other particles are
    scored with it, so it is the log-likelihood to use when poses scored in different
    calls are compared (Metropolis moves, searches keeping earlier candidates): eq. 1's
    normalisation over the batch would add a batch-dependent constant."""
    tac = _iou_table(iou_tactile, None, "iou_tactile")
    n = None if tac is None else tac.shape[0]
    vis = _iou_table(iou_vision, n, "iou_vision")
    if vis is not None:
        n = vis.shape[0]
    if n is None:
        raise ValueError("at least one of iou_tactile and iou_vision must be given")
    if tac is None:
        tac = np.zeros((n, 0))
    if vis is None:
        vis = np.zeros((n, 0))
    g, v = sensor_weights(
        ~np.all(np.isnan(tac), axis=0), ~np.all(np.isnan(vis), axis=0), gamma, nu, renormalise
    )
    # eq. 2; isolated NaNs (and absent sensors, whose weight is 0) contribute nothing.
    return np.nan_to_num(tac, nan=0.0) @ g + np.nan_to_num(vis, nan=0.0) @ v


def eq2_weights(configured: list[float | None], share: float) -> np.ndarray:
    """Eq. 1-2 weights (n,) of one modality's sensors present in a frame: a sensor's
    configured ``weight`` where set (0 switches the sensor off), else an equal part of the
    modality's ``share`` (1/N_T or 1/N_V of it)."""
    default = share / len(configured) if configured else 0.0
    return np.array([default if w is None else float(w) for w in configured], dtype=float)


def scaled_weights(names: list[str], weights: np.ndarray, factor: Callable[[str], float]) -> np.ndarray:
    """Eq. 1-2 weights (n,) of one modality's sensors ``names`` with the consistency watch's
    ``factor(name)`` applied (``filter.health.SensorConsistency``); while a sensor of the
    modality keeps its full weight, the modality's share is kept (the others take up what a
    scaled-down sensor loses, as if it were absent)."""
    factors = np.array([factor(n) for n in names])
    if not np.any(factors != 1.0):
        return weights
    scaled = weights * factors
    full = factors == 1.0
    if np.any(full) and scaled.sum() > 0:
        scaled[full] *= (weights.sum() - scaled[~full].sum()) / scaled[full].sum()
    return scaled


def mask_area_factor(observation: Observation, name: str, full_weight_px: float) -> float:
    """The factor in [0, 1] of sensor ``name``'s eq. 2 weight for its observed mask's size:
    the mask's area [image pixels] over ``full_weight_px`` (``filter.camera_full_weight_px``),
    at most 1; 1 when ``full_weight_px`` is 0. An IoU of masks a few pixels across changes
    from 0 to 1 with a one-pixel shift, so at full weight it outweighs every larger mask of
    the frame (beyond the paper)."""
    if full_weight_px <= 0:
        return 1.0
    return min(1.0, observation.area_px(name) / full_weight_px)


def configured_weights(cfg: Config, observation: Observation) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 2 weights (gamma, nu) of the observed sensors before the consistency watch: a
    sensor's ``weight``, or an equal part of its modality's share (``sensors.tactile_share``
    when cameras and touch are both enabled, else all of it). Each modality keeps its share on
    frames where the other has no image (sensors at different rates): rescaling touch to the
    whole score on tactile-only frames let the pads pull the rotations they cannot place."""
    both = ("vision" in cfg.modalities and bool(cfg.sensors.cameras)
            and "tactile" in cfg.modalities and bool(cfg.sensors.tactile))
    share = cfg.sensors.tactile_share
    t_share, v_share = (share, 1.0 - share) if both else (1.0, 1.0)
    tactile = {t.name: t.weight for t in cfg.sensors.tactile}
    cameras = {c.name: c.weight for c in cfg.sensors.cameras}
    return (eq2_weights([tactile[n] for n in observation.tactile], t_share),
            eq2_weights([cameras[n] for n in observation.cameras], v_share))


class Likelihood:
    """``log p(y_k | T_ee_object)`` of one frame (eq. 6 in log space): eq. 2's weighted IoU
    sum over the temperature (eq. 1, unnormalised), plus eq. 9's contact term.

    frame, observation : the frame and its ``Observation`` (ROIs, occluders, observed masks).
    contact : the frame's contact state (None or False: no contact term).
    weight_factor : the consistency watch's factor per sensor name (see ``scaled_weights``).

    Eq. 2's weights: each sensor's configured ``weight``, or an equal part of its modality's
    share (``configured_weights``), times ``weight_factor`` and, for a camera, its observed
    mask's ``mask_area_factor`` (``filter.camera_full_weight_px``).

    Calling it scores poses (N, 4, 4) -> (N,), NaN / +inf made -inf (``filter.result``),
    and counts every pose scored and every invalid value (``evaluated``, ``invalid``): the
    frame's searches and refinement all go through it.
    """

    def __init__(self, cfg: Config, scene: SceneModel, frame: Frame, observation: Observation, contact: bool | None,
                 weight_factor: Callable[[str], float] = lambda name: 1.0):
        self.cfg = cfg
        self.scene = scene
        self.frame = frame
        self.observation = observation
        self.base_gamma, self.base_nu = configured_weights(cfg, observation)
        self.gamma = scaled_weights(observation.tactile, self.base_gamma, weight_factor)
        full_px = cfg.filter.camera_full_weight_px
        self.nu = scaled_weights(observation.cameras, self.base_nu,
                                 lambda name: weight_factor(name) * mask_area_factor(observation, name, full_px))
        self.contact = bool(contact) and scene.has_contact_model
        self.gel_distance_m = {t.name: t.gel_distance_m for t in cfg.sensors.tactile}
        self.evaluated = 0
        self.invalid = 0
        self.calls = 0
        self.seconds = 0.0  # wall time spent scoring (render + IoU + contact)
        # while a list (``record``): every call's poses, per-sensor terms and log-likelihoods
        self.tape: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    def add_counts(self, other: Likelihood) -> None:
        """Count ``other``'s scored poses, invalid values, calls and time as this one's (a frame
        redone with new masks reports the work of both)."""
        self.evaluated += other.evaluated
        self.invalid += other.invalid
        self.calls += other.calls
        self.seconds += other.seconds

    def informative(self, ious: dict[str, float]) -> dict[str, bool]:
        """Per observed sensor, whether its IoUs at a pose (``sensor_ious``) say anything: not
        switched off by a configured weight of 0, and not both masks empty (a tactile sensor
        out of contact agrees trivially). The consistency watch judges only these."""
        obs = self.observation
        weights = np.concatenate([self.base_gamma, self.base_nu])
        return {n: bool(w > 0 and (obs.masks[n].any() or obs.outside[n] > 0 or ious[n] < 1.0))
                for n, w in zip(obs.sensors, weights)}

    def ious(self, T_ee_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IoU of every observed mask with the mask rendered at each pose (N, 4, 4):
        (N, N_T) tactile and (N, N_V) camera tables, in ``observation``'s sensor order."""
        obs = self.observation
        return self.iou_table(obs.tactile, T_ee_object), self.iou_table(obs.cameras, T_ee_object)

    def iou_table(self, names: list[str], T_ee_object: np.ndarray) -> np.ndarray:
        """IoU (N, len(names)) of the observed sensors ``names`` at each pose (N, 4, 4)."""
        out = np.empty((len(T_ee_object), len(names)))
        for j, n in enumerate(names):
            out[:, j] = self.sensor_iou(n, T_ee_object)
        return out

    def sensor_iou(self, name: str, T_ee_object: np.ndarray) -> np.ndarray:
        """IoU (N,) of observed sensor ``name``'s mask with the mask rendered at each pose
        (N, 4, 4) in its ROI (tactile: the gel contact; cameras: the silhouette behind the
        occluders); the area of the observed mask outside the ROI counts as missed."""
        obs, frame, renderer = self.observation, self.frame, self.scene.renderer
        T = frame.T_sensor_object(name, T_ee_object)
        if name in obs.tactile:
            return renderer.score_masks(
                OBJECT_ID, T, frame.tactile[name].camera, obs.rois[name], obs.masks[name], mode="tactile",
                gel_distance_m=self.gel_distance_m[name],
                penetration_threshold_m=self.cfg.masking.tactile_depth_threshold_m, observed_outside=obs.outside[name],
                depth_limit_m=self.depth_limit(name))
        return renderer.score_masks(OBJECT_ID, T, frame.cameras[name].camera, obs.rois[name], obs.masks[name],
                                    obs.occluders[name], observed_outside=obs.outside[name])

    def depth_limit(self, name: str) -> np.ndarray | None:
        """Tactile sensor ``name``'s depth (h, w) [m, sensor z] nearer than which a pose presses
        the gel deeper than measured (``masking.tactile_depth_tolerance_m`` beyond the
        indentation the sensor measured in each ROI pixel, ``Observation.indentation``); None
        without a measured indentation."""
        measured = self.observation.indentation.get(name)
        if measured is None:
            return None
        return self.gel_distance_m[name] - measured - self.cfg.masking.tactile_depth_tolerance_m

    def rendered_masks(self, T_ee_object: np.ndarray) -> dict[str, np.ndarray]:
        """Per observed sensor, the mask (h, w) bool rendered at one pose (4, 4) in its ROI,
        as ``ious`` renders it (tactile: the gel contact; cameras: the silhouette behind the
        occluders): the mask each observed mask is compared with."""
        obs, frame, renderer = self.observation, self.frame, self.scene.renderer
        out = {}
        for n in obs.sensors:
            T = frame.T_sensor_object(n, np.asarray(T_ee_object)[None])
            if n in obs.tactile:
                m = renderer.render_masks(OBJECT_ID, T, frame.tactile[n].camera, obs.rois[n], mode="tactile",
                                          gel_distance_m=self.gel_distance_m[n],
                                          penetration_threshold_m=self.cfg.masking.tactile_depth_threshold_m)
            else:
                m = renderer.render_masks(OBJECT_ID, T, frame.cameras[n].camera, obs.rois[n], obs.occluders[n])
            out[n] = np.asarray(m[0], dtype=bool)
        return out

    def sensor_ious(self, T_ee_object: np.ndarray) -> dict[str, float]:
        """Per observed sensor, the IoU of its mask with the mask rendered at one pose (4, 4)."""
        iou_t, iou_v = self.ious(T_ee_object[None])
        return {n: float(v) for n, v in zip(self.observation.sensors, np.concatenate([iou_t[0], iou_v[0]]))}

    def contour_evidence(self, T_ee_object: np.ndarray) -> np.ndarray:
        """Per camera with image derivatives (``observation.gradients``), the contour evidence
        (N, n_cameras) at each pose (N, 4, 4): the sum over the visible contour samples of the
        gradient across the contour minus the background level, per 100 px of contour
        (``estimator/edges.py``) [CIE Lab units per image pixel]."""
        obs, frame, renderer, e = self.observation, self.frame, self.scene.renderer, self.cfg.edges
        out = np.empty((len(T_ee_object), len(obs.gradients)))
        for j, (n, edge) in enumerate(obs.gradients.items()):
            total, count = renderer.contour_gradient(
                OBJECT_ID, frame.T_sensor_object(n, T_ee_object), frame.cameras[n].camera, obs.rois[n], edge.gx,
                edge.gy, obs.occluders[n], e.spacing_px, e.occluder_margin_px, e.occluder_depth_step, e.crease_deg)
            out[:, j] = (total - e.background_factor * edge.background * count) * e.spacing_px / 100.0
        return out

    def sensor_terms(self, iou_t: np.ndarray, iou_v: np.ndarray) -> np.ndarray:
        """Each observed sensor's eq. 2 term over the temperature (N, S) [nats], columns in
        ``observation.sensors`` order, from the IoU tables (N, N_T) / (N, N_V) of ``ious``; an
        undefined IoU counts 0, as in the score."""
        ious = np.concatenate([np.asarray(iou_t, dtype=np.float64), np.asarray(iou_v, dtype=np.float64)], axis=1)
        return np.nan_to_num(ious, nan=0.0) * np.concatenate([self.gamma, self.nu]) / self.cfg.filter.temperature

    def record(self) -> None:
        """Keep every pose scored from now on (``tape``): its per-sensor terms (``sensor_terms``)
        and log-likelihood, e.g. for the first frame's leave-one-out check; ``stop`` ends it."""
        self.tape = []

    def stop(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """End ``record``: the poses (M, 4, 4), sensor terms (M, S) and log-likelihoods (M,)
        scored since, or None when nothing was."""
        tape, self.tape = self.tape, None
        if not tape:
            return None
        poses, terms, ll = zip(*tape)
        return np.concatenate(poses), np.concatenate(terms), np.concatenate(ll)

    def scored(self, T_ee_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Log-likelihoods (N,) of poses ``T_ee_object`` (N, 4, 4) and their per-sensor terms
        (N, S) [nats] (``sensor_terms``); kept on the ``tape`` while recording."""
        return self._score(T_ee_object, terms=True)

    def __call__(self, T_ee_object: np.ndarray) -> np.ndarray:
        """Log-likelihoods (N,) of poses ``T_ee_object`` (N, 4, 4); kept on the ``tape`` while
        recording."""
        return self._score(T_ee_object, terms=self.tape is not None)[0]

    def _score(self, T_ee_object: np.ndarray, terms: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Log-likelihoods (N,) and, when ``terms`` (or recording), the per-sensor terms (N, S)."""
        t0 = time.perf_counter()
        iou_t, iou_v = self.ious(T_ee_object)
        ll = self.log_likelihood(T_ee_object, iou_t, iou_v, self.gamma, self.nu, t0)
        table = self.sensor_terms(iou_t, iou_v) if terms else None
        if self.tape is not None:
            self.tape.append((np.array(T_ee_object, dtype=np.float64), table, ll))
        return ll, table

    def log_likelihood(self, T_ee_object: np.ndarray, iou_t: np.ndarray, iou_v: np.ndarray, gamma: np.ndarray,
                       nu: np.ndarray, t0: float) -> np.ndarray:
        """Eq. 6 of poses (N, 4, 4) from their IoU tables (N, N_T) / (N, N_V) and eq. 2's weights
        for those columns: the weighted IoU sum over the temperature, the contour and contact
        terms; counted as scored poses, with the wall time since ``t0``."""
        score = visuo_tactile_score(iou_t, iou_v, gamma if len(gamma) else None,
                                    nu if len(nu) else None, renormalise=False) / self.cfg.filter.temperature
        if self.observation.gradients:
            score = score + self.cfg.edges.gain * self.contour_evidence(T_ee_object).sum(axis=1)
        if self.contact:
            phi = self.scene.phi(self.frame.T_world_ee @ T_ee_object)
            c = self.cfg.contact
            score = score + log_contact_likelihood(phi, True, c.margin_m, c.softness_m)
            if c.penetration_softness_m is not None:
                score = score + log_penetration_likelihood(phi, c.penetration_tolerance_m, c.penetration_softness_m)
        score, invalid = valid_log_likelihood(score)
        self.invalid += invalid
        self.evaluated += len(score)
        self.calls += 1
        self.seconds += time.perf_counter() - t0
        return score


# poses rendered at a time by ``ProposalLikelihood``: bounds the (chunk, h, w) masks to a few MB
_PROPOSAL_CHUNK = 256


class ProposalLikelihood:
    """The frame's log-likelihood with each pose choosing its own camera masks: Algorithm 2 per
    pose, the best IoU of its rendered silhouette among the camera's belief-free proposals.

    likelihood : the frame's ``Likelihood`` (its tactile masks, contour and contact terms).
    proposals : camera name -> ``observation.ProposalSet``, the backend's zero-shot proposals
      in the grasp prior's window (``ObservationModel.proposal_sets``), made from the image
      alone.

    The frame's own camera masks are chosen by the belief's best particles (Algorithm 1) and
    seed a GrabCut proposal from its silhouettes, so a belief in a wrong mode picks evidence
    that agrees with it and scores itself highest. Here no belief enters the evidence: every
    pose is scored against the proposals it explains best, so two poses far apart compare on
    equal terms. Eq. 2's weights are the configured ones, without the consistency watch's
    factors (the watch judges sensors against the belief). The proposals are coarser than the
    frame's masks (a window covering the whole prior, downsampled to ``filter.roi_size_px``),
    so the scale is only for comparing poses with each other, not with ``Likelihood``.
    """

    def __init__(self, likelihood: Likelihood, proposals: dict):
        self.likelihood = likelihood
        obs = likelihood.observation
        self.proposals = proposals
        self.cameras = [n for n in obs.cameras if n in proposals]
        self.gamma = likelihood.base_gamma
        self.nu = np.array([likelihood.base_nu[obs.cameras.index(n)] for n in self.cameras])

    def camera_ious(self, T_ee_object: np.ndarray) -> np.ndarray:
        """Per pose (N, 4, 4) and camera, the best IoU among the camera's proposals (N, N_V)."""
        L = self.likelihood
        out = np.empty((len(T_ee_object), len(self.cameras)))
        for j, name in enumerate(self.cameras):
            found, img = self.proposals[name], L.frame.cameras[name]
            T = L.frame.T_sensor_object(name, T_ee_object)
            for s in range(0, len(T), _PROPOSAL_CHUNK):
                rendered = L.scene.renderer.render_masks(OBJECT_ID, T[s : s + _PROPOSAL_CHUNK], img.camera, found.roi,
                                                         L.observation.occluders[name])
                out[s : s + _PROPOSAL_CHUNK, j] = iou_matrix(rendered, found.masks).max(axis=1)
        return out

    def __call__(self, T_ee_object: np.ndarray) -> np.ndarray:
        """Log-likelihoods (N,) of poses ``T_ee_object`` (N, 4, 4)."""
        t0 = time.perf_counter()
        L = self.likelihood
        iou_t = L.iou_table(L.observation.tactile, T_ee_object)
        return L.log_likelihood(T_ee_object, iou_t, self.camera_ious(T_ee_object), self.gamma, self.nu, t0)
