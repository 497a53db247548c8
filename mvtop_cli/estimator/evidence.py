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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry.se3 import perturb_about_origin


@dataclass(frozen=True)
class EvidenceReport:
    """One frame's evidence diagnostic.

    sensor_iou : per observed sensor, the IoU of its mask with the mask rendered at the estimate
    log_likelihood : the log-likelihood of the estimate [nats]
    likelihood_sigma : (6,) the likelihood's width at the estimate along x, y, z [m] (object
        origin along the ee axes) and rx, ry, rz [rad] (rotation in ee axes about the object
        origin), ``inf`` where it is flat or rising at the probe step
    """

    sensor_iou: dict[str, float]
    log_likelihood: float
    likelihood_sigma: np.ndarray

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
        """Whether the likelihood falls along all six axes at the probe's step (no ``inf`` width)."""
        return bool(np.all(np.isfinite(self.likelihood_sigma)))

    def as_dict(self) -> dict:
        """JSON-ready form (``inf`` as null)."""
        num = finite_or_none
        return {"sensor_iou": {k: round(float(v), 6) for k, v in self.sensor_iou.items()},
                "min_iou": None if self.min_iou is None else round(self.min_iou, 6),
                "log_likelihood": num(self.log_likelihood),
                "likelihood_sigma_translation_m": [num(v) for v in self.likelihood_sigma[:3]],
                "likelihood_sigma_rotation_deg": [num(np.degrees(v)) for v in self.likelihood_sigma[3:]]}


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
