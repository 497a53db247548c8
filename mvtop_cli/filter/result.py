"""What one filter update hands back, and the filter's one policy for invalid likelihoods.

A log-likelihood function maps particles ``T_ee_object (N, 4, 4)`` to ``(N,)`` values:
``-inf`` means impossible; NaN and ``+inf`` (a degenerate render or distance) mean "no valid
score" and become ``-inf`` (weight zero), counted, never carried into comparisons, searches
or the estimate. ``valid_log_likelihood`` is that policy; the filter loop, the SMC
refinement, the searches and the estimator's likelihood all apply it through this module.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .particles import ParticleSet, Spread

LogLikelihoodFn = Callable[[np.ndarray], np.ndarray]
"""Maps particles ``T_ee_object (N, 4, 4)`` to log-likelihoods ``(N,)``. ``-inf`` means
impossible; NaN and ``+inf`` are treated as invalid (weight zero) and counted."""

FLAG_NAMES = ("degenerate_weights", "ess_collapsed", "estimate_jump", "tempering_forced")


def valid_log_likelihood(values: np.ndarray) -> tuple[np.ndarray, int]:
    """``values`` (N,) as float64 with NaN and ``+inf`` replaced by ``-inf``, and how many
    were replaced."""
    out = np.asarray(values, dtype=np.float64)
    invalid = np.isnan(out) | np.isposinf(out)
    n_invalid = int(invalid.sum())
    return (np.where(invalid, -np.inf, out) if n_invalid else out), n_invalid


def evaluate(log_likelihood_fn: LogLikelihoodFn, poses: np.ndarray) -> tuple[np.ndarray, int]:
    """Call the model on read-only ``poses`` (N, 4, 4); returns the valid log-likelihoods
    (N,) and the invalid count. Raises ``ValueError`` on a result of the wrong shape."""
    n = len(poses)
    view = np.array(poses, dtype=np.float64)
    view.flags.writeable = False
    out = np.asarray(log_likelihood_fn(view), dtype=np.float64)
    if out.shape != (n,):
        raise ValueError(f"log_likelihood_fn returned shape {out.shape}, expected ({n},)")
    return valid_log_likelihood(out)


@dataclass(frozen=True)
class StepResult:
    """What one filter update produced.

    particles : ParticleSet
      The particles to carry to the next frame (resampled if ``resampled``).
    estimate : (4, 4) float
      ``T_ee_object`` estimate: weighted SE(3) mean of the updated particles. ``update``
      takes it before resampling (resampling only adds Monte-Carlo noise to the mean);
      ``refine`` takes it from its final, equally weighted particles.
    spread : Spread
      Mean and covariance of the same weighted set.
    ess : float
      Effective sample size of the updated weights, before resampling.
    resampled : bool
      Whether the returned particles were resampled.
    log_evidence : float
      Estimate of ``log p(y_k | y_1:k-1)``, the log of the weighted mean likelihood of
      this frame (``-inf`` when every likelihood was zero or invalid).
    diagnostics : dict
      ``flags`` (list of raised flag names: ``degenerate_weights``, ``ess_collapsed``,
      ``estimate_jump``, ``tempering_forced``), the matching booleans,
      ``invalid_log_likelihood`` (count of NaN / +inf values received),
      ``evaluated_poses`` (how many poses were scored), ``min_ess`` (the smallest ESS of
      the update: of the weights for ``update``, of any tempering stage for ``refine``)
      and ``ess_collapse_threshold``, the jump and its allowance, and for ``refine`` the
      per-stage ``betas``, ``stage_ess``, ``acceptance_rates`` and
      ``likelihood_evaluations``. A frame redone after a collapse (see
      ``ParticleFilter``'s ``collapse_retry_iterations``) adds ``collapse_retry``: the
      iterations of the redo, ``min_ess_before`` and ``recovered`` (the redo's ESS stayed
      above the threshold).
    log_likelihoods : (N,) float or None
      The valid log-likelihoods of ``particles`` under this frame's model, where the update
      computed them (``refine``: its final particles'); None otherwise.
    """

    particles: ParticleSet
    estimate: np.ndarray
    spread: Spread
    ess: float
    resampled: bool
    log_evidence: float
    diagnostics: dict = field(default_factory=dict)
    log_likelihoods: np.ndarray | None = None

    @property
    def flags(self) -> tuple[str, ...]:
        """Names of the failure modes detected in this update."""
        return tuple(self.diagnostics.get("flags", ()))


def finish(diagnostics: dict, flags: list[str]) -> None:
    """Record the raised ``flags`` in ``diagnostics``: a boolean per flag name and the list."""
    for name in FLAG_NAMES:
        diagnostics[name] = name in flags
    diagnostics["flags"] = list(dict.fromkeys(flags))
