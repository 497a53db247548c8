"""Prior particles and the in-hand motion model (Algorithm 4, Sec. IV-D).

Noise convention, used by every function here: a perturbation ``(dt, dw)`` moves the
object's origin by ``dt`` [m] along the **ee axes** and rotates the object by the rotation
vector ``dw`` [rad], also in **ee axes**, **about the object's own origin**::

    R_ee_object' = Exp(dw) @ R_ee_object        t_ee_object' = t_ee_object + dt

So a rotation never moves the object origin (no lever arm), and the sigmas mean exactly
what ``se3.pose_spread`` measures (translation of the origin in the parent frame,
rotation as a left perturbation), which is what ``ParticleSet.spread`` reports. For
isotropic sigmas the distribution is the same as a right perturbation in the object
frame (``se3.perturb``), because ``R dt`` and ``R dw`` are then distributed like
``dt`` and ``dw``; the distinction only matters for per-axis sigmas and box priors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import se3
from .particles import ParticleSet


def perturb_about_origin(T_ee_object: np.ndarray, dt_ee: np.ndarray, dw_ee: np.ndarray) -> np.ndarray:
    """Apply perturbations to poses (..., 4, 4) with the module's convention.

    dt_ee : (..., 3) float
      Translation of the object origin along the ee axes [m].
    dw_ee : (..., 3) float
      Rotation vector in ee axes [rad], about the object origin.
    """
    T = np.asarray(T_ee_object, dtype=np.float64)
    R = se3.rotvec_to_matrix(dw_ee) @ T[..., :3, :3]
    return se3.make_pose(R, T[..., :3, 3] + np.asarray(dt_ee, dtype=np.float64))


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


@dataclass(frozen=True)
class MotionModel:
    """Algorithm 4: the object follows the end effector rigidly, plus Gaussian slip noise.

    Because particles are ``T_ee_object``, ``H(u_k)`` (moving with the end effector) is
    the identity on the state; only the noise ``N(0, sigma)`` remains, with the high
    sigmas while the robot is in external contact (``c_k = 1``, the grasp may slip) and
    the low sigmas otherwise. Sigmas are per-axis standard deviations [m] / [rad] with the
    module's noise convention (ee axes, about the object origin).
    """

    sigma_low_translation_m: float
    sigma_low_rotation_rad: float
    sigma_high_translation_m: float
    sigma_high_rotation_rad: float

    def __post_init__(self) -> None:
        for name in (
            "sigma_low_translation_m",
            "sigma_low_rotation_rad",
            "sigma_high_translation_m",
            "sigma_high_rotation_rad",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"MotionModel.{name} must be finite and >= 0, got {value!r}")

    def sigmas(self, contact: bool) -> tuple[float, float]:
        """(translation [m], rotation [rad]) standard deviations for this contact state."""
        if contact is None:
            raise ValueError("contact must be True or False; map a missing contact signal first")
        if bool(contact):
            return self.sigma_high_translation_m, self.sigma_high_rotation_rad
        return self.sigma_low_translation_m, self.sigma_low_rotation_rad

    def propagate(
        self, particles: ParticleSet, contact: bool, rng: np.random.Generator, scale: float = 1.0
    ) -> ParticleSet:
        """Move particles one step (Algorithm 4, line 7); weights are kept.

        ``scale`` multiplies both sigmas (e.g. to account for a longer time between
        frames than the sigmas were tuned for).
        """
        if not np.isfinite(scale) or scale < 0:
            raise ValueError(f"scale must be finite and >= 0, got {scale!r}")
        st, sr = self.sigmas(contact)
        n = len(particles)
        dt = rng.standard_normal((n, 3)) * (st * scale)
        dw = rng.standard_normal((n, 3)) * (sr * scale)
        return particles.with_poses(perturb_about_origin(particles.poses, dt, dw))
