"""Weighted pose particles: object poses in the end-effector frame with log-space weights (eq. 4)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry import se3

Fold = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""Optional canonicalisation of poses handed in by the model: ``(poses (N, 4, 4), reference
(4, 4)) -> poses (N, 4, 4)``, each pose replaced by an equivalent one (same likelihood, e.g. a
symmetric object's pose turned by a symmetry) closest to ``reference``. The filter never looks
inside it (the estimator's is ``estimator.symmetry.SymmetryFold``)."""


def log_sum_exp(a: np.ndarray) -> float:
    """``log(sum(exp(a)))`` of a 1-D float array, stable: ``scipy.special.logsumexp``'s own
    steps for real 1-D input (the maxima summed apart, ``log1p`` of the rest; the direct sum
    where that is not finite), so it gives the same bits in about a third of its time on the
    few-hundred-element arrays the filter sums thousands of times a run (500 elements: 12 us
    against 38 us on this 2-core machine). ``-inf`` when empty."""
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    if a.size == 0:
        return -np.inf
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        a_max = a.max(keepdims=True)
        at_max = a == a_max
        m = np.sum(at_max, keepdims=True, dtype=np.float64)
        s = np.sum(np.exp(np.where(at_max, -np.inf, a) - a_max), keepdims=True, dtype=np.float64)
        s = np.where(s == 0, s, s / m)
        out = np.log1p(s) + np.log(m) + a_max
        if not np.isfinite(out[0]):
            out = np.log(np.sum(np.exp(a), keepdims=True))
    return float(out[0])


def normalise_log_weights(log_weights: np.ndarray) -> np.ndarray:
    """Log-weights (N,) shifted so that ``exp`` of them sums to one (log-sum-exp, stable).

    Entries of ``-inf`` (zero weight) stay ``-inf``. Raises ``ValueError`` when no entry is
    finite, or any is NaN or ``+inf``: such weights cannot be normalised.
    """
    lw = np.asarray(log_weights, dtype=np.float64)
    if np.isnan(lw).any() or np.isposinf(lw).any():
        raise ValueError("log-weights contain NaN or +inf")
    if not np.isfinite(lw).any():
        raise ValueError("all log-weights are -inf (every weight is zero)")
    return lw - log_sum_exp(lw)


def ess_from_log_weights(log_weights: np.ndarray) -> float:
    """Effective sample size ``(sum w)^2 / sum w^2`` of unnormalised log-weights (N,).

    Computed as ``exp(2 lse(lw) - lse(2 lw))`` so that weights spanning hundreds of orders
    of magnitude neither overflow nor underflow. Ranges from 1 (one particle holds all the
    weight) to N (uniform weights).
    """
    lw = normalise_log_weights(log_weights)
    return float(np.exp(-log_sum_exp(2.0 * lw)))


def largest_exponent(
    log_weights: np.ndarray, log_likelihood: np.ndarray, max_exponent: float, goal_ess: float
) -> float:
    """The largest ``b`` in [0, max_exponent] whose tempered reweighting ``w L^b`` keeps an
    effective sample size of at least ``goal_ess`` (bisection, 60 halvings; ``max_exponent``
    itself when it keeps it). Particles with a non-finite log-likelihood (N,) get weight zero.

    The one tempering rule of the filter: the SMC refinement's adaptive stages (Jasra et al.
    2011) and the searches' tempered resampling of a scored population both use it."""
    finite = np.isfinite(log_likelihood)
    ll = np.where(finite, log_likelihood - np.max(log_likelihood[finite]), 0.0)
    base = np.where(finite, log_weights, -np.inf)

    def ess(b: float) -> float:
        return ess_from_log_weights(base + b * ll)

    if ess(max_exponent) >= goal_ess:
        return float(max_exponent)
    lo, hi = 0.0, float(max_exponent)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if ess(mid) >= goal_ess:
            lo = mid
        else:
            hi = mid
    return lo


@dataclass(frozen=True)
class Spread:
    """How widely a particle set is spread around its mean.

    mean : (4, 4) float
      Weighted mean pose ``T_ee_object`` (see ``se3.weighted_mean``).
    covariance : (6, 6) float
      Weighted covariance in the tangent space at the mean, ordered
      (x, y, z [m], rx, ry, rz [rad]): translation of the object origin along the ee axes,
      rotation as a left perturbation in ee axes (see ``se3.pose_spread``).
    """

    mean: np.ndarray
    covariance: np.ndarray

    @property
    def translation_std_m(self) -> float:
        """Per-axis translation standard deviation [m], averaged over x, y, z (sqrt(trace / 3)).

        For an isotropic Gaussian with per-axis sigma ``s`` this is ``s``."""
        return float(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0) / 3.0))

    @property
    def rotation_std_rad(self) -> float:
        """Per-axis rotation standard deviation [rad], averaged over the three axes."""
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0) / 3.0))

    @property
    def translation_rms_m(self) -> float:
        """Root-mean-square distance of the object origin from the mean [m] (sqrt(trace))."""
        return float(np.sqrt(max(np.trace(self.covariance[:3, :3]), 0.0)))

    @property
    def rotation_rms_rad(self) -> float:
        """Root-mean-square rotation angle from the mean [rad] (sqrt(trace))."""
        return float(np.sqrt(max(np.trace(self.covariance[3:, 3:]), 0.0)))


@dataclass(frozen=True)
class ParticleSet:
    """Pose particles and their log-weights, which always travel together.

    poses : (N, 4, 4) float
      ``T_ee_object`` hypotheses. The object is rigidly held, so following the end
      effector between frames (Algorithm 4's ``H(u_k)``) leaves these unchanged; world
      poses are ``T_world_ee @ poses``.
    log_weights : (N,) float
      Unnormalised log-weights; ``-inf`` marks a zero weight. At least one must be finite.

    Both arrays are copied and made read-only, so a set is never changed in place.
    """

    poses: np.ndarray
    log_weights: np.ndarray

    def __post_init__(self) -> None:
        poses = np.array(self.poses, dtype=np.float64)
        lw = np.array(self.log_weights, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
            raise ValueError(f"poses must have shape (N, 4, 4) with N > 0, got {poses.shape}")
        if lw.shape != (len(poses),):
            raise ValueError(f"log_weights must have shape ({len(poses)},), got {lw.shape}")
        normalise_log_weights(lw)  # validates: no NaN / +inf, at least one finite
        poses.flags.writeable = False
        lw.flags.writeable = False
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "log_weights", lw)

    @classmethod
    def uniform(cls, poses: np.ndarray) -> ParticleSet:
        """Equally weighted particles (log-weights ``-log N``)."""
        n = len(poses)
        return cls(poses, np.full(n, -np.log(n)))

    def __len__(self) -> int:
        return len(self.poses)

    def normalised_log_weights(self) -> np.ndarray:
        """Log-weights (N,) normalised so their exponentials sum to one."""
        return normalise_log_weights(self.log_weights)

    def weights(self) -> np.ndarray:
        """Normalised weights (N,) summing to one."""
        return np.exp(self.normalised_log_weights())

    def ess(self) -> float:
        """Effective sample size in [1, N], from the log-weights (see ``ess_from_log_weights``)."""
        return ess_from_log_weights(self.log_weights)

    def mean(self) -> np.ndarray:
        """Weighted mean pose (4, 4) ``T_ee_object``: translations averaged, rotations by
        quaternion (Markley) averaging (``se3.weighted_mean``), i.e. the paper's estimate
        (Sec. IV-C) with a proper rotation average."""
        return se3.weighted_mean(self.poses, self.weights())

    def spread(self, fold: Fold | None = None) -> Spread:
        """Weighted mean and tangent-space covariance (``se3.pose_spread``). With ``fold``
        (see ``Fold``), of the folded poses: first onto the heaviest particle, then, for a
        reference that does not depend on which particle that was, onto the mean of that."""
        poses = self.poses if fold is None else self.folded(fold)
        mean, cov = se3.pose_spread(poses, self.weights())
        return Spread(mean=mean, covariance=cov)

    def folded(self, fold: Fold) -> np.ndarray:
        """The poses (N, 4, 4) folded (``Fold``) onto the weighted mean of their fold onto the
        heaviest particle."""
        w = self.weights()
        first = fold(self.poses, self.poses[int(np.argmax(w))])
        return fold(self.poses, se3.weighted_mean(first, w))

    def with_log_weights(self, log_weights: np.ndarray) -> ParticleSet:
        """The same poses with other log-weights (N,)."""
        return ParticleSet(self.poses, log_weights)

    def with_poses(self, poses: np.ndarray) -> ParticleSet:
        """Other poses (N, 4, 4) with the same log-weights."""
        return ParticleSet(poses, self.log_weights)
