"""Searches around the filter: the first frame's global search of the grasp prior and the
per-frame local re-search, both cross-entropy searches, and the tempered resampling that
turns a scored search population into N particles.

A particle filter of a few hundred particles cannot cover a +-3 mm / +-10 deg prior at the
scale where IoU scores discriminate (a fraction of a millimetre), so on the first frame the
estimator first looks for the likelihood's basin: sample many poses, keep the best tenth, fit
a Gaussian to them in the tangent space, sample again from it (widened), and repeat. This is
the role of Algorithm 1's pose candidates; the filter's tempered refinement then starts from
that basin with the exact likelihood. Later frames run a short search started from the
belief to check that the belief sits at the likelihood's peak.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..geometry import se3
from .particles import ParticleSet, largest_exponent
from .resampling import resample
from .result import valid_log_likelihood


def cross_entropy_search(
    initial: np.ndarray,
    log_likelihood: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
    rounds: int = 12,
    elite_fraction: float = 0.1,
    widen: float = 1.5,
    floor_translation_m: float = 5e-5,
    floor_rotation_rad: float = np.radians(0.05),
) -> tuple[np.ndarray, np.ndarray]:
    """Refine the pose population ``initial`` (M, 4, 4) towards high ``log_likelihood``.

    Each round scores the population, keeps the ``elite_fraction`` best, and replaces the rest
    with draws from a Gaussian fitted to the elite (translation in the parent frame, rotation
    as a left perturbation, covariance scaled by ``widen**2`` plus a floor [m] / [rad] per
    axis). Returns the final population (M, 4, 4) and its valid log-likelihoods (M,).
    """
    pop = np.asarray(initial, dtype=np.float64)
    M = len(pop)
    n_elite = max(2, int(round(elite_fraction * M)))
    floor = np.diag([floor_translation_m**2] * 3 + [floor_rotation_rad**2] * 3)
    ll = valid_log_likelihood(log_likelihood(pop))[0]
    for _ in range(rounds):
        order = np.argsort(-ll, kind="stable")
        elite, elite_ll = pop[order[:n_elite]], ll[order[:n_elite]]
        mean, cov = se3.pose_spread(elite)
        L = np.linalg.cholesky(cov * widen**2 + floor)
        d = rng.standard_normal((M - n_elite, 6)) @ L.T
        fresh = se3.make_pose(se3.rotvec_to_matrix(d[:, 3:]) @ mean[:3, :3], mean[:3, 3] + d[:, :3])
        fresh_ll = valid_log_likelihood(log_likelihood(fresh))[0]
        pop = np.concatenate([elite, fresh])
        ll = np.concatenate([elite_ll, fresh_ll])
    return pop, ll


def local_search(
    particles: ParticleSet,
    log_likelihood: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
    sigma_translation_m: float,
    sigma_rotation_rad: float,
    **search,
) -> tuple[np.ndarray, np.ndarray]:
    """A cross-entropy search (``search``: its keyword arguments) started from the belief
    ``particles`` resampled uniformly and widened by the given per-axis sigmas [m] / [rad]
    (``se3.perturb_about_origin``): the likelihood's best pose near the belief. A wrong or
    lagging belief shows as a searched pose that fits the observation much better than any
    particle."""
    n = len(particles)
    idx = rng.integers(0, n, n)
    dt = rng.standard_normal((n, 3)) * sigma_translation_m
    dw = rng.standard_normal((n, 3)) * sigma_rotation_rad
    start = se3.perturb_about_origin(particles.poses[idx], dt, dw)
    return cross_entropy_search(start, log_likelihood, rng, **search)


def tempered_resample(
    poses: np.ndarray, log_likelihood: np.ndarray, n: int, resampling: str, rng: np.random.Generator
) -> ParticleSet:
    """``n`` equally weighted particles from a scored search population (M, 4, 4): weights
    ``L^b`` with the largest ``b`` <= 1 that keeps an effective sample size of ``n``
    (``particles.largest_exponent``; 0: uniform over the finite), then resampling. At least
    one log-likelihood (M,) must be finite."""
    finite = np.isfinite(log_likelihood)
    b = largest_exponent(np.zeros(len(log_likelihood)), log_likelihood, 1.0, n)
    shifted = np.where(finite, log_likelihood - np.max(log_likelihood[finite]), 0.0)
    weighted = ParticleSet(poses, np.where(finite, b * shifted, -np.inf))
    return resample(weighted, resampling, rng, n_out=n)
