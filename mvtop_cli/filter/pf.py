"""The pose particle filter loop (Algorithm 3), kept apart from the model it runs.

The model is three things handed in: a motion model (Algorithm 4, ``Motion``), a
resampling scheme name, and per frame a ``log_likelihood_fn`` mapping particles
``T_ee_object (N, 4, 4)`` to log-likelihoods ``(N,)`` (eq. 6 in log space: the
visuo-tactile log-score of eq. 1-2 plus the contact log-likelihood of eq. 8-9). The
filter never looks inside them.

Two ways to use a frame's observation, each of which uses it exactly once, chosen in one
place (``assimilate``):

* ``update``: Algorithm 3 as printed, one importance update ``log w += log p(y | x)``
  then resampling when the ESS falls below a threshold.
* ``refine``: an annealed (tempered) SMC sampler for the same posterior
  ``p(x | y_1:k) ∝ p(x | y_1:k-1) p(y_k | x)`` (``smc.TemperedRefinement``). One importance
  update with ~1000 particles cannot reach sub-millimetre precision when the prior is
  ±3 mm / ±10° and the IoU likelihood is sharp: almost no particle lands in the likelihood's
  peak, so the weights collapse onto a few poor particles. ``refine`` instead moves the
  particles into the peak while keeping the posterior honest.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .health import JumpCheck, check_jump
from .particles import Fold, ParticleSet, Spread, log_sum_exp
from .resampling import get_scheme, resample_if_needed
from .result import LogLikelihoodFn, StepResult, evaluate, finish
from .smc import TemperedRefinement, check_shrink


class Motion(Protocol):
    """What the filter needs of a motion model (Algorithm 4)."""

    def sigmas(self, contact: bool) -> tuple[float, float]:
        """Per-axis (translation [m], rotation [rad]) noise for this contact state."""

    def propagate(self, particles: ParticleSet, contact: bool, rng: np.random.Generator,
                  scale: float = 1.0) -> ParticleSet:
        """The particles moved one step."""


class ParticleFilter:
    """Pose particle filter (Algorithm 3) on ``T_ee_object`` particles.

    motion : Motion
      Algorithm 4's motion model (the estimator's ``MotionModel``).
    resampling : str
      Registered resampling scheme name (``resampling.available_schemes()``).
    ess_threshold_fraction : float in [0, 1]
      ``update`` resamples when ``ESS < ess_threshold_fraction * N``.
    rng : numpy.random.Generator
      The only source of randomness: same seed, same results.
    ess_collapse_fraction : float
      An ESS below this fraction of N raises the ``ess_collapsed`` flag, with a floor of
      2 particles (at most N / 2): default 1%, i.e. 5 of 500 particles, 2 of 100 (an ESS
      under 2 means one particle holds most of the weight).
    jump_sigmas : float
      ``step`` raises ``estimate_jump`` for an estimate further from the previous belief
      than this many RMS spreads of the predicted belief (``check_jump``).
    refine_iterations : int
      Default for ``step``: 0 runs ``update``, more runs ``refine`` with that many
      iterations.
    refine_shrink : float in (0, 1)
      Default proposal-scale adaptation factor for ``refine``.
    floor_translation_m, floor_rotation_rad : float
      Smallest kernel / proposal standard deviation per axis used by ``refine``
      (default 0.05 mm and 0.05°), and the smallest spread the jump check allows for.
    refine_target_ess_fraction : float in (0, 1)
      Fraction of the ESS each adaptive tempering stage of ``refine`` keeps (0.5, the
      usual choice, halves it per stage).
    collapse_retry_iterations : int
      0 (default): an ESS collapse is only flagged. More: a frame whose ESS collapsed is
      redone once from the same predicted particles by ``refine`` with
      ``max(collapse_retry_iterations, 3 * iterations)`` iterations (the observation
      still counts once), whose smaller tempering steps and Metropolis moves rejuvenate
      the particles; ``ess_collapsed`` stays flagged and ``collapse_retry`` says whether
      the redo kept its ESS above the threshold. Frames without a collapse are
      unaffected.
    posterior_sweeps : int or None
      At most this many of ``refine``'s Metropolis sweeps at the posterior (tempering
      exponent 1); None: all its iterations run (``smc.TemperedRefinement``).
    fold : callable or None
      The model's canonicalisation of poses (``particles.Fold``; a symmetric object's
      ``estimator.symmetry.SymmetryFold``): the estimate and covariance are those of the
      folded particles, the jump check folds the estimate onto the previous mean, and
      ``refine`` folds the predicted particles onto their mean before its tangent chart, so
      a belief spread freely about a symmetry axis stays within the chart. None: the
      particles as they are.
    """

    def __init__(
        self,
        motion: Motion,
        resampling: str = "systematic",
        ess_threshold_fraction: float = 0.5,
        rng: np.random.Generator | None = None,
        *,
        ess_collapse_fraction: float = 0.01,
        jump_sigmas: float = 5.0,
        refine_iterations: int = 0,
        refine_shrink: float = 0.5,
        floor_translation_m: float = 5e-5,
        floor_rotation_rad: float = float(np.deg2rad(0.05)),
        refine_target_ess_fraction: float = 0.5,
        collapse_retry_iterations: int = 0,
        posterior_sweeps: int | None = None,
        fold: Fold | None = None,
    ) -> None:
        if not isinstance(rng, np.random.Generator):
            raise TypeError("rng must be a numpy.random.Generator (no global random state)")
        get_scheme(resampling)
        if not 0.0 <= ess_threshold_fraction <= 1.0:
            raise ValueError(f"ess_threshold_fraction must be in [0, 1], got {ess_threshold_fraction!r}")
        if not 0.0 <= ess_collapse_fraction <= 1.0:
            raise ValueError(f"ess_collapse_fraction must be in [0, 1], got {ess_collapse_fraction!r}")
        if not 0.0 < refine_target_ess_fraction < 1.0:
            raise ValueError(f"refine_target_ess_fraction must be in (0, 1), got {refine_target_ess_fraction!r}")
        if int(refine_iterations) < 0:
            raise ValueError(f"refine_iterations must be >= 0, got {refine_iterations!r}")
        if int(collapse_retry_iterations) < 0:
            raise ValueError(f"collapse_retry_iterations must be >= 0, got {collapse_retry_iterations!r}")
        check_shrink(refine_shrink)
        if floor_translation_m <= 0 or floor_rotation_rad <= 0:
            raise ValueError("floor_translation_m and floor_rotation_rad must be > 0")
        self.motion = motion
        self.resampling = resampling
        self.ess_threshold_fraction = float(ess_threshold_fraction)
        self.rng = rng
        self.ess_collapse_fraction = float(ess_collapse_fraction)
        self.jump_sigmas = float(jump_sigmas)
        self.refine_iterations = int(refine_iterations)
        self.refine_shrink = float(refine_shrink)
        self.floor_translation_m = float(floor_translation_m)
        self.floor_rotation_rad = float(floor_rotation_rad)
        self.refine_target_ess_fraction = float(refine_target_ess_fraction)
        self.collapse_retry_iterations = int(collapse_retry_iterations)
        self.fold = fold
        self.smc = TemperedRefinement(
            resampling, rng, shrink=self.refine_shrink,
            floor_translation_m=self.floor_translation_m, floor_rotation_rad=self.floor_rotation_rad,
            target_ess_fraction=self.refine_target_ess_fraction, collapse_threshold=self.collapse_threshold,
            collapse_retry_iterations=self.collapse_retry_iterations, posterior_sweeps=posterior_sweeps, fold=fold,
        )

    # -- the loop ---------------------------------------------------------------------

    def predict(self, particles: ParticleSet, contact: bool, scale: float = 1.0) -> ParticleSet:
        """Algorithm 3 line 4: the motion model (Algorithm 4)."""
        return self.motion.propagate(particles, contact, self.rng, scale)

    def step(
        self,
        particles: ParticleSet,
        contact: bool,
        log_likelihood_fn: LogLikelihoodFn,
        *,
        refine_iterations: int | None = None,
    ) -> StepResult:
        """One frame of Algorithm 3: ``predict``, then ``assimilate`` the observation
        (``refine_iterations``, default ``self.refine_iterations``), then the jump check
        of the estimate against ``particles``, the previous frame's result (or the initial
        particles ``X_init``)."""
        k = self.refine_iterations if refine_iterations is None else int(refine_iterations)
        result = self.assimilate(self.predict(particles, contact), log_likelihood_fn, k)
        jump = self.check_jump(particles.spread(self.fold), result.estimate, contact)
        d = result.diagnostics
        d.update(contact=bool(contact), jump_translation_m=jump.translation_m, jump_rotation_rad=jump.rotation_rad,
                 allowed_translation_m=jump.allowed_translation_m, allowed_rotation_rad=jump.allowed_rotation_rad)
        if jump.jumped:
            finish(d, list(result.flags) + ["estimate_jump"])
        return result

    def assimilate(self, predicted: ParticleSet, log_likelihood_fn: LogLikelihoodFn, iterations: int,
                   n_out: int | None = None) -> StepResult:
        """The frame's observation applied to the ``predicted`` particles: ``update``
        (``iterations`` = 0) or ``refine`` with that many iterations, returning ``n_out``
        particles (default as many as predicted; ``refine`` only)."""
        if iterations > 0:
            return self.refine(predicted, log_likelihood_fn, iterations, n_out=n_out)
        if n_out is not None and n_out != len(predicted):
            raise ValueError("the single importance update keeps the particle count: n_out needs iterations > 0")
        return self.update(predicted, log_likelihood_fn)

    def update(self, particles: ParticleSet, log_likelihood_fn: LogLikelihoodFn) -> StepResult:
        """Algorithm 3 lines 5-9 on predicted particles: ``log w += log p(y | x)``
        (line 7), estimate from the weighted set, then importance resampling when
        ``ESS < ess_threshold_fraction * N`` (line 9, adaptive).

        If no particle has a finite, valid log-likelihood the observation is dropped:
        the predicted weights are kept and ``degenerate_weights`` is flagged.
        """
        prior_lw = particles.normalised_log_weights()
        log_lik, n_invalid = evaluate(log_likelihood_fn, particles.poses)
        lw = prior_lw + log_lik
        flags: list[str] = []
        if np.isfinite(lw).any():
            log_evidence = log_sum_exp(lw)
            posterior = particles.with_log_weights(lw - log_evidence)
        else:
            log_evidence = -np.inf
            posterior = particles.with_log_weights(prior_lw)
            flags.append("degenerate_weights")
        ess = posterior.ess()
        spread = posterior.spread(self.fold)
        if flags:  # degenerate: hand the predicted particles on untouched
            out, resampled = posterior, False
        else:
            out, resampled = resample_if_needed(posterior, self.ess_threshold_fraction, self.resampling, self.rng)
        diagnostics: dict = {
            "invalid_log_likelihood": n_invalid,
            "likelihood_evaluations": 1,
            "evaluated_poses": len(particles),
            "min_ess": float(ess),
            "ess_collapse_threshold": self.collapse_threshold(len(particles)),
        }
        if "degenerate_weights" not in flags and ess < self.collapse_threshold(len(particles)):
            flags.append("ess_collapsed")
        finish(diagnostics, flags)
        result = StepResult(out, spread.mean, spread, ess, resampled, log_evidence, diagnostics)
        if "ess_collapsed" in flags and self.collapse_retry_iterations > 0:
            return self.smc.redo_collapsed(particles, log_likelihood_fn, result, 0, None)
        return result

    def refine(
        self,
        particles: ParticleSet,
        log_likelihood_fn: LogLikelihoodFn,
        iterations: int | None = None,
        shrink: float | None = None,
        n_out: int | None = None,
    ) -> StepResult:
        """Annealed update of the *predicted* ``particles`` with ``iterations`` (default
        ``self.refine_iterations``) tempering stages and Metropolis sweeps, into ``n_out``
        particles (default as many): see ``smc.TemperedRefinement``."""
        return self.smc(particles, log_likelihood_fn, self.refine_iterations if iterations is None else iterations,
                        shrink, n_out)

    # -- checks -----------------------------------------------------------------------

    def collapse_threshold(self, n: int) -> float:
        """The ESS below which ``n`` particles count as collapsed: ``ess_collapse_fraction
        * n``, at least 2, at most ``n / 2``."""
        return min(max(self.ess_collapse_fraction * n, 2.0), 0.5 * n)

    def check_jump(self, previous: Spread, estimate: np.ndarray, contact: bool) -> JumpCheck:
        """The one jump check (``health.check_jump``): ``estimate`` (4, 4) against the
        previous frame's belief ``previous`` and the motion noise of this contact state; with a
        ``fold``, the estimate's equivalent closest to the previous mean."""
        if self.fold is not None:
            estimate = self.fold(np.asarray(estimate, dtype=np.float64)[None], previous.mean)[0]
        sigma_t, sigma_r = self.motion.sigmas(bool(contact))
        return check_jump(previous, estimate, sigma_t, sigma_r, self.jump_sigmas, self.floor_translation_m,
                          self.floor_rotation_rad)
