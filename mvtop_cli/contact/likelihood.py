"""Contact likelihood of a pose particle from its signed distance (M-VTOP eq. 8-9), and the
non-penetration factor mvtop adds to it under contact (a part cannot be inside the receptacle)."""

from __future__ import annotations

import numpy as np
from scipy.special import expit, log_expit


def _logit(phi, margin_m: float, softness_m: float) -> np.ndarray:
    if not softness_m > 0:
        raise ValueError(f"softness_m (sigma_d) must be positive, got {softness_m}")
    return (float(margin_m) - np.asarray(phi, dtype=np.float64)) / float(softness_m)


def contact_likelihood(phi, contact: bool, margin_m: float, softness_m: float) -> np.ndarray:
    """p(c_k | x) per particle (eq. 9): σ((τ_c − φ) / σ_d) (eq. 8) when contact is reported,
    1 when it is not.

    Parameters
    ----------
    phi : (N,) float
        Signed distance [m] between object and environment per particle, > 0 contact-free.
    contact : bool
        Whether contact is reported at this step (c_k).
    margin_m : float
        τ_c [m]: the signed distance at which the likelihood is 1/2.
    softness_m : float
        σ_d [m] > 0: the width of the logistic's transition.

    Returns
    -------
    (N,) float in [0, 1], non-increasing in φ. φ = +inf gives 0 and φ = −inf gives 1.
    """
    z = _logit(phi, margin_m, softness_m)
    if not contact:
        return np.ones_like(z)
    return expit(z)


def log_contact_likelihood(phi, contact: bool, margin_m: float, softness_m: float) -> np.ndarray:
    """log p(c_k | x) per particle, the log of :func:`contact_likelihood`, computed as
    ``log_expit`` so that it stays finite and accurate for large |(τ_c − φ) / σ_d|
    (≈ (τ_c − φ) / σ_d far from contact, ≈ 0 deep in it) instead of rounding to log 0."""
    z = _logit(phi, margin_m, softness_m)
    if not contact:
        return np.zeros_like(z)
    return log_expit(z)


def log_penetration_likelihood(phi, tolerance_m: float, softness_m: float) -> np.ndarray:
    """log p(no penetration | x) per particle: log σ((φ + τ_p) / σ_p), beyond the paper.

    Eq. 8-9 only reward a pose for touching the environment (φ <= τ_c); a pose sunk into the
    receptacle scores as well as one resting on it, so under contact the belief can tilt or
    sink the part through the surface it is pressed against. This factor is 1/2 at a
    penetration of ``tolerance_m`` (τ_p [m], what the signed-distance grid's interpolation
    and a real contact's compliance leave open) and falls off over ``softness_m`` (σ_p [m]):
    about -(-φ - τ_p) / σ_p nats for deeper penetration, about 0 for φ > τ_p.

    phi : (N,) float, signed distance [m] between object and environment, < 0 penetrating.
    """
    if not softness_m > 0:
        raise ValueError(f"softness_m (sigma_p) must be positive, got {softness_m}")
    return log_expit((np.asarray(phi, dtype=np.float64) + float(tolerance_m)) / float(softness_m))
