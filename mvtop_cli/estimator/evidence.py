"""How well a frame's evidence pins the estimate: the per-frame evidence diagnostic.

Two numbers a user can read next to the estimate (track.csv, summary.json):

- how well the estimate explains each sensor: the IoU of each observed mask with the mask
  rendered at the estimate (eq. 2's terms, one per sensor), and their minimum;
- how ambiguous the likelihood is around the estimate: its curvature along each of the six
  pose axes, probed by moving the estimate one step either way (the log-likelihood of eq. 1-2
  and 8-9, as the filter uses it). A log-likelihood that falls by ``drop`` nats over a step
  ``h`` behaves like a Gaussian of standard deviation ``h / sqrt(2 drop)`` on that axis (the
  Laplace approximation); a flat or rising log-likelihood gives ``inf`` there: the evidence
  does not pin that axis at the step's scale (a central difference reads a quadratic's curvature
  wherever the estimate sits on it, so being beside the peak does not make an axis flat).

This is a reading of the evidence, not of the particles: a belief that has collapsed further
than its evidence supports shows as a particle spread far below these widths.

A probe along one axis at a time misses a ridge that runs obliquely: a part sliding along an axis
the pads cannot see while it turns a little about another can keep every mask as it is, so the
log-likelihood stays flat along the combined motion while each pure axis step costs many nats.
The profile widths (``profile_widths``) read the likelihood along each axis with the other five
coordinates free: at each offset, the best score a small search of the other coordinates finds
(the profile likelihood, whose fall gives an axis's marginal width rather than its conditional
one). On a simulated touch-only conn1 grasp (M-TOP, seed 1097) that ended 1.67 mm off along the
connector's length, every pure x step of 0.5 mm cost 8-13 nats, while the truth scored 1 nat above
the estimate and the profile fell by 1.9 nats at 1 mm and 4.6 at 2 mm. An axis that the latest
profile leaves open counts as open (``EvidenceReport.pinned``) until the next profile, towards the
run's ``suspect_estimate`` warning as well as into the covariance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..filter.result import valid_log_likelihood
from ..geometry.se3 import perturb_about_origin

# the profile's search never narrows below this fraction of its starting spread: it keeps
# looking about its elite's mean instead of collapsing onto one pose
_PROFILE_SPREAD_FLOOR = 0.05


@dataclass(frozen=True)
class EvidenceReport:
    """One frame's evidence diagnostic.

    sensor_iou : per observed sensor, the IoU of its mask with the mask rendered at the estimate
    log_likelihood : the log-likelihood of the estimate [nats]
    likelihood_sigma : (6,) the likelihood's width at the estimate along x, y, z [m] (object
        origin along the ee axes) and rx, ry, rz [rad] (rotation in ee axes about the object
        origin), ``inf`` where it is flat or rising at the probe step
    profile_sigma : (6,) the profile widths of the latest frame that measured them
        (``profile_widths``, ``output.evidence_profile``), same axes and units; None: not measured
    """

    sensor_iou: dict[str, float]
    log_likelihood: float
    likelihood_sigma: np.ndarray
    profile_sigma: np.ndarray | None = None

    @property
    def min_iou(self) -> float | None:
        """The worst-explained sensor's IoU (None without observed sensors)."""
        return min(self.sensor_iou.values()) if self.sensor_iou else None

    @property
    def sigma_translation_m(self) -> float:
        """The widest of the three translation widths [m]."""
        return float(np.max(self.likelihood_sigma[:3]))

    @property
    def sigma_rotation_deg(self) -> float:
        """The widest of the three rotation widths [deg]."""
        return float(np.degrees(np.max(self.likelihood_sigma[3:])))

    @property
    def pinned(self) -> bool:
        """Whether the evidence pins all six axes: the likelihood falls along each at the probe's
        step and, where the profile was measured, at every profile offset (no ``inf`` in
        ``widths``). A profile that finds a pose as good as the estimate within its reach along an
        axis leaves that axis open however sharp the one-axis probe is (a ridge)."""
        return bool(np.all(np.isfinite(self.widths)))

    @property
    def widths(self) -> np.ndarray:
        """(6,) the wider of the probe's and the profile's width per axis: what the evidence
        leaves open about the estimate (the probe's alone without a profile)."""
        if self.profile_sigma is None:
            return self.likelihood_sigma
        return np.maximum(self.likelihood_sigma, self.profile_sigma)

    def as_dict(self) -> dict:
        """JSON-ready form (``inf`` as null)."""
        num = finite_or_none
        out = {"sensor_iou": {k: round(float(v), 6) for k, v in self.sensor_iou.items()},
               "min_iou": None if self.min_iou is None else round(self.min_iou, 6),
               "log_likelihood": num(self.log_likelihood),
               "likelihood_sigma_translation_m": [num(v) for v in self.likelihood_sigma[:3]],
               "likelihood_sigma_rotation_deg": [num(np.degrees(v)) for v in self.likelihood_sigma[3:]]}
        if self.profile_sigma is not None:
            out["profile_sigma_translation_m"] = [num(v) for v in self.profile_sigma[:3]]
            out["profile_sigma_rotation_deg"] = [num(np.degrees(v)) for v in self.profile_sigma[3:]]
        return out


def finite_or_none(value: float | None) -> float | None:
    """``value`` as a JSON number, None when missing or not finite (a width the evidence leaves open)."""
    return None if value is None or not np.isfinite(value) else float(value)


def likelihood_widths(log_likelihood: Callable[[np.ndarray], np.ndarray], T_ee_object: np.ndarray,
                      step_translation_m: float, step_rotation_rad: float) -> tuple[float, np.ndarray]:
    """The log-likelihood at ``T_ee_object`` (4, 4) and its width (6,) along each pose axis from
    a central difference with the given steps (see the module docstring); 13 poses scored."""
    steps = np.array([step_translation_m] * 3 + [step_rotation_rad] * 3, dtype=np.float64)
    delta = np.zeros((12, 6))
    for k in range(6):
        delta[2 * k, k], delta[2 * k + 1, k] = steps[k], -steps[k]
    probes = perturb_about_origin(np.broadcast_to(T_ee_object, (12, 4, 4)), delta[:, :3], delta[:, 3:])
    ll = log_likelihood(np.concatenate([np.asarray(T_ee_object, dtype=np.float64)[None], probes]))
    centre, side = ll[0], ll[1:].reshape(6, 2)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # -inf scores: nan drops, inf widths
        drop = centre - side.mean(axis=1)  # nats lost half a step's square away: d^2 / (2 sigma^2)
        sigma = np.where(drop > 0, steps / np.sqrt(2.0 * drop), np.inf)
    if not np.isfinite(centre):
        sigma = np.full(6, np.inf)
    return float(centre), sigma


def profile_widths(log_likelihood: Callable[[np.ndarray], np.ndarray], T_ee_object: np.ndarray,
                   centre_ll: float, max_translation_m: float, max_rotation_rad: float,
                   scale_translation_m: float, scale_rotation_rad: float, rng: np.random.Generator,
                   population: int, rounds: int, elite_fraction: float) -> np.ndarray:
    """The likelihood's profile widths (6,) about ``T_ee_object`` (4, 4), whose log-likelihood is
    ``centre_ll``: along each axis (as ``likelihood_widths``), at offsets of 1/4, 1/2 and all of
    ``max_translation_m`` [m] / ``max_rotation_rad`` [rad] either way, the best log-likelihood a
    cross-entropy search of the other five coordinates finds (``population`` poses a round for
    ``rounds`` rounds, the ``elite_fraction`` best refitted, from a Gaussian of standard deviation
    ``scale_*`` about the estimate, never narrower than ``_PROFILE_SPREAD_FLOOR`` of it; the first
    round holds the pure axis step, so the profile never falls faster than the probe). An offset
    ``d`` whose profile falls by ``drop`` nats gives a Gaussian width ``|d| / sqrt(2 drop)`` (the
    Laplace approximation of the profile); the axis's width is the widest of its six offsets,
    ``inf`` where some offset scores as well as the estimate or better. All 36 searches share each
    round's likelihood call (``rounds`` calls of 36 x ``population`` poses)."""
    fractions = np.array([-1.0, -0.5, -0.25, 0.25, 0.5, 1.0])
    reach = np.array([max_translation_m] * 3 + [max_rotation_rad] * 3)
    scale = np.array([scale_translation_m] * 3 + [scale_rotation_rad] * 3)
    if not np.isfinite(centre_ll):
        return np.full(6, np.inf)
    axis = np.repeat(np.arange(6), len(fractions))  # (G,) the held axis of each search
    offset = (reach[:, None] * fractions[None, :]).ravel()  # (G,) its offset there
    groups = len(axis)
    held = np.zeros((groups, 6), dtype=bool)
    held[np.arange(groups), axis] = True
    n_elite = max(2, int(round(elite_fraction * population)))
    mean = np.where(held, offset[:, None], 0.0)  # (G, 6) tangent offsets about the estimate
    sd = np.where(held, 0.0, scale[None, :])
    best = np.full(groups, -np.inf)
    T = np.asarray(T_ee_object, dtype=np.float64)
    for r in range(rounds):
        d = mean[:, None, :] + rng.standard_normal((groups, population, 6)) * sd[:, None, :]
        if r == 0:
            d[:, 0] = mean  # the pure axis step
        flat = d.reshape(-1, 6)
        poses = perturb_about_origin(np.broadcast_to(T, (len(flat), 4, 4)), flat[:, :3], flat[:, 3:])
        ll = valid_log_likelihood(log_likelihood(poses))[0].reshape(groups, population)
        best = np.maximum(best, ll.max(axis=1))
        order = np.argsort(-ll, axis=1, kind="stable")[:, :n_elite]
        elite = np.take_along_axis(d, order[:, :, None], axis=1)
        mean = np.where(held, offset[:, None], elite.mean(axis=1))
        sd = np.where(held, 0.0, np.maximum(elite.std(axis=1), _PROFILE_SPREAD_FLOOR * scale[None, :]))
    with np.errstate(divide="ignore", invalid="ignore"):
        drop = centre_ll - best
        sigma = np.where(drop > 0, np.abs(offset) / np.sqrt(2.0 * drop), np.inf)
    return sigma.reshape(6, len(fractions)).max(axis=1)


def evidence_covariance(likelihood_sigma: np.ndarray, prior_sigma: np.ndarray, factor: float = 1.0) -> np.ndarray:
    """The covariance (6, 6) the evidence alone supports about the estimate: the likelihood's
    widths (6,) times ``factor`` squared on the diagonal, an axis it does not pin (``inf``) taking
    the grasp prior's standard deviation ``prior_sigma`` (6,) instead (the evidence leaves the
    prior's spread there), never wider than the prior. Added to the particles' covariance for the
    reported one (``output.covariance``; ``factor`` is ``output.evidence_width_factor``)."""
    prior_sigma = np.asarray(prior_sigma, dtype=np.float64)
    sigma = np.where(np.isfinite(likelihood_sigma), factor * np.asarray(likelihood_sigma, dtype=np.float64),
                     prior_sigma)
    return np.diag(np.minimum(sigma, prior_sigma) ** 2)


def leave_one_out(terms: np.ndarray, log_likelihood: np.ndarray, elsewhere: np.ndarray, terms_estimate: np.ndarray,
                  ll_estimate: float) -> tuple[np.ndarray, np.ndarray]:
    """Whether one sensor alone holds the estimate against all the others: per sensor ``s``, the
    best of the scored poses ``elsewhere`` (M,) bool (another mode than the estimate's) by the
    log-likelihood without ``s``'s eq. 2 term, and by how many nats the other sensors (with the
    contact term) prefer it to the estimate there.

    terms, log_likelihood : (M, S) per-sensor eq. 2 terms [nats] and (M,) log-likelihoods of the
        scored poses (``Likelihood.record``);
    terms_estimate, ll_estimate : (S,) and the log-likelihood of the estimate.

    Returns the gains (S,) [nats] (``-inf`` where no pose lies elsewhere or none scores finitely)
    and the index (S,) into the scored poses of each sensor's best pose (-1 where none). When the
    estimate is the joint peak, the left-out sensor loses at least the gain there: a large gain
    means the sensors contradict each other, and the estimate rests on that one sensor's word."""
    terms = np.asarray(terms, dtype=np.float64)
    ll = np.asarray(log_likelihood, dtype=np.float64)
    ok = np.asarray(elsewhere, dtype=bool) & np.isfinite(ll)
    gains = np.full(terms.shape[1], -np.inf)
    index = np.full(terms.shape[1], -1, dtype=np.int64)
    if not ok.any():
        return gains, index
    rows = np.flatnonzero(ok)
    others = ll[rows, None] - terms[rows]  # (m, S)
    best = np.argmax(others, axis=0)
    index = rows[best]
    gains = others[best, np.arange(terms.shape[1])] - (ll_estimate - np.asarray(terms_estimate, dtype=np.float64))
    return gains, index
