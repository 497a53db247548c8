"""Coarse global search of the grasp prior for the first frame (cross-entropy method).

A particle filter of a few hundred particles cannot cover a +-3 mm / +-10 deg prior at the
scale where IoU scores discriminate (a fraction of a millimetre), so on the first frame the
estimator first looks for the likelihood's basin: sample many poses, keep the best tenth, fit
a Gaussian to them in the tangent space, sample again from it (widened), and repeat. This is
the role of Algorithm 1's pose candidates; the filter's tempered refinement then starts from
that basin with the exact likelihood.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..geometry import se3


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
    as a left perturbation, covariance scaled by ``widen**2`` plus a floor). Returns the final
    population (M, 4, 4) and its log-likelihoods (M,).
    """
    pop = np.asarray(initial, dtype=np.float64)
    M = len(pop)
    n_elite = max(2, int(round(elite_fraction * M)))
    floor = np.diag([floor_translation_m**2] * 3 + [floor_rotation_rad**2] * 3)
    ll = _finite(log_likelihood(pop))
    for _ in range(rounds):
        order = np.argsort(-ll, kind="stable")
        elite, elite_ll = pop[order[:n_elite]], ll[order[:n_elite]]
        mean, cov = se3.pose_spread(elite)
        L = np.linalg.cholesky(cov * widen**2 + floor)
        d = rng.standard_normal((M - n_elite, 6)) @ L.T
        fresh = se3.make_pose(se3.rotvec_to_matrix(d[:, 3:]) @ mean[:3, :3], mean[:3, 3] + d[:, :3])
        fresh_ll = _finite(log_likelihood(fresh))
        pop = np.concatenate([elite, fresh])
        ll = np.concatenate([elite_ll, fresh_ll])
    return pop, ll


def _finite(ll: np.ndarray) -> np.ndarray:
    return np.nan_to_num(np.asarray(ll, dtype=np.float64), nan=-np.inf, posinf=-np.inf, neginf=-np.inf)
