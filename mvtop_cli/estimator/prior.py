"""The grasp prior: where the object can be in the gripper before any image (Algorithm 3,
line 2: ``X_init``), drawn as uniform boxes or Gaussians about the nominal grasp, with the
region the searches may explore.

Draws use the motion model's convention (``se3.perturb_about_origin``): the object origin
moves along the ee axes, the rotation vector is in ee axes about the object origin.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..config import GraspPrior
from ..filter.particles import ParticleSet
from ..geometry import se3
from ..geometry.se3 import perturb_about_origin

LogLikelihood = Callable[[np.ndarray], np.ndarray]


def _per_axis(value: float | np.ndarray, name: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
    return v


def _check_nominal(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_ee_object_nominal must have shape (4, 4), got {T.shape}")
    return T


def init_from_prior(
    T_ee_object_nominal: np.ndarray,
    sigma_translation_m: float | np.ndarray,
    sigma_rotation_rad: float | np.ndarray,
    n: int,
    rng: np.random.Generator,
) -> ParticleSet:
    """Equally weighted particles drawn from a Gaussian around the nominal grasp
    (Algorithm 3, line 2: ``X_init``).

    T_ee_object_nominal : (4, 4) float
      Nominal object pose in the ee frame.
    sigma_translation_m, sigma_rotation_rad : float or (3,) float
      Standard deviation per ee axis [m] / [rad], applied with the module's convention
      (origin moved along ee axes, rotation in ee axes about the object origin).
    Returns ``n`` particles with uniform weights.
    """
    T0 = _check_nominal(T_ee_object_nominal)
    st = _per_axis(sigma_translation_m, "sigma_translation_m")
    sr = _per_axis(sigma_rotation_rad, "sigma_rotation_rad")
    dt = rng.standard_normal((n, 3)) * st
    dw = rng.standard_normal((n, 3)) * sr
    return ParticleSet.uniform(perturb_about_origin(np.broadcast_to(T0, (n, 4, 4)), dt, dw))


def init_uniform_box(
    T_ee_object_nominal: np.ndarray,
    half_width_translation_m: float | np.ndarray,
    half_width_rotation_rad: float | np.ndarray,
    n: int,
    rng: np.random.Generator,
) -> ParticleSet:
    """Equally weighted particles drawn uniformly from a box around the nominal grasp.

    Matches a grasp offset drawn as "up to ±a per axis and ±b per axis": ``dt`` uniform in
    ``[-a, a]^3`` along the ee axes and the rotation vector ``dw`` uniform in
    ``[-b, b]^3`` (ee axes, about the object origin). When the nominal rotation maps ee
    axes onto object axes up to sign (as in the nominal grasp, object +z = ee -z), the
    same box expressed in object axes is the same set.

    half_width_translation_m, half_width_rotation_rad : float or (3,) float
      Box half-widths per ee axis [m] / [rad].
    """
    T0 = _check_nominal(T_ee_object_nominal)
    a = _per_axis(half_width_translation_m, "half_width_translation_m")
    b = _per_axis(half_width_rotation_rad, "half_width_rotation_rad")
    dt = rng.uniform(-1.0, 1.0, (n, 3)) * a
    dw = rng.uniform(-1.0, 1.0, (n, 3)) * b
    return ParticleSet.uniform(perturb_about_origin(np.broadcast_to(T0, (n, 4, 4)), dt, dw))


class GraspPriorModel:
    """The config's grasp prior over ``T_ee_object``: samples, and the searches' region.

    prior : config.GraspPrior
      Nominal pose, distribution (``uniform`` box of half-widths or ``gaussian`` of sigmas,
      per ee axis) and its translation [m] / rotation [deg] size.
    search_bound : float
      The searches stay within this many half-widths (uniform) of the nominal grasp, or
      twice as many sigmas (gaussian): room for slip beyond the prior, no more.
    """

    def __init__(self, prior: GraspPrior, search_bound: float):
        self.prior = prior
        self.T_ee_object_nominal = prior.pose.matrix()
        self.search_bound = float(search_bound)

    @property
    def sigma(self) -> np.ndarray:
        """The prior's standard deviation (6,) per ee axis: x, y, z [m], rx, ry, rz [rad] (a
        uniform box's half-width over sqrt 3)."""
        g = self.prior
        k = 1.0 / np.sqrt(3.0) if g.distribution == "uniform" else 1.0
        return k * np.array([g.translation_m] * 3 + [np.radians(g.rotation_deg)] * 3)

    def covariance_about(self, T_ee_object: np.ndarray, fold: Callable | None = None) -> np.ndarray:
        """The second moment (6, 6) about pose ``T_ee_object`` (4, 4) of a grasp drawn from the
        prior, in the tangent space of ``se3.pose_spread`` (x, y, z [m], rx, ry, rz [rad], ee
        axes, left perturbation): the prior's covariance plus ``d d^T``, ``d`` the nominal
        grasp's offset from the pose (from its symmetric equivalent nearest the nominal, with
        ``fold``: ``estimator.symmetry.SymmetryFold``). What the truth's spread about an
        estimate is when the evidence cannot be trusted: anywhere the prior allows, and an
        estimate that wandered off the nominal grasp is that much further from most of it."""
        T_nom = self.T_ee_object_nominal
        T = np.asarray(T_ee_object, dtype=np.float64)
        if fold is not None:
            T = fold(T[None], T_nom)[0]
        d = np.concatenate([T_nom[:3, 3] - T[:3, 3], se3.matrix_to_rotvec(T_nom[:3, :3] @ T[:3, :3].T)])
        return np.diag(self.sigma**2) + np.outer(d, d)

    def sample(self, n: int, rng: np.random.Generator) -> ParticleSet:
        """``n`` equally weighted particles ``T_ee_object`` drawn from the prior."""
        g = self.prior
        draw = init_uniform_box if g.distribution == "uniform" else init_from_prior
        return draw(self.T_ee_object_nominal, g.translation_m, np.radians(g.rotation_deg), n, rng)

    def within(self, T_ee_object: np.ndarray) -> np.ndarray:
        """(N,) bool: poses (N, 4, 4) within the search region, per ee axis."""
        g = self.prior
        T_nom = self.T_ee_object_nominal
        dt = np.abs(T_ee_object[:, :3, 3] - T_nom[:3, 3])
        dw = np.abs(se3.matrix_to_rotvec(T_ee_object[:, :3, :3] @ T_nom[:3, :3].T))
        k = self.search_bound if g.distribution == "uniform" else 2.0 * self.search_bound
        return np.all(dt <= k * g.translation_m, axis=1) & np.all(dw <= k * np.radians(g.rotation_deg), axis=1)

    def bounded(self, log_likelihood: LogLikelihood) -> LogLikelihood:
        """``log_likelihood`` restricted to the search region (``-inf`` outside): the searches
        draw from Gaussians fitted to their elites, which a likelihood that is flat in some
        direction (one modality alone) lets wander far outside any plausible grasp."""

        def fn(T_ee_object: np.ndarray) -> np.ndarray:
            return np.where(self.within(T_ee_object), log_likelihood(T_ee_object), -np.inf)

        return fn
