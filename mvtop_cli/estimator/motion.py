"""The in-hand motion model (Algorithm 4, Sec. IV-D): the object follows the end effector,
with more slip noise while the part is in external contact.

Noise convention (``se3.perturb_about_origin``): a perturbation ``(dt, dw)`` moves the
object's origin by ``dt`` [m] along the **ee axes** and rotates the object by the rotation
vector ``dw`` [rad], also in **ee axes**, **about the object's own origin**::

    R_ee_object' = Exp(dw) @ R_ee_object        t_ee_object' = t_ee_object + dt

So a rotation never moves the object origin (no lever arm), and the sigmas mean exactly
what ``se3.pose_spread`` measures (translation of the origin in the parent frame,
rotation as a left perturbation), which is what ``ParticleSet.spread`` reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..filter.particles import ParticleSet
from ..geometry.se3 import perturb_about_origin


@dataclass(frozen=True)
class MotionModel:
    """Algorithm 4: the object follows the end effector rigidly, plus Gaussian slip noise.

    Because particles are ``T_ee_object``, ``H(u_k)`` (moving with the end effector) is
    the identity on the state; only the noise ``N(0, sigma)`` remains, with the high
    sigmas while the robot is in external contact (``c_k = 1``, the grasp may slip) and
    the low sigmas otherwise. Sigmas are per-axis standard deviations [m] / [rad] with the
    module's noise convention (ee axes, about the object origin); ``translation_axis_scale``
    multiplies the translation sigmas along the ee x, y, z axes (``sigmas`` returns them
    unscaled, the largest an axis can have).
    """

    sigma_low_translation_m: float
    sigma_low_rotation_rad: float
    sigma_high_translation_m: float
    sigma_high_rotation_rad: float
    translation_axis_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        scale = np.asarray(self.translation_axis_scale, dtype=float)
        if scale.shape != (3,) or not np.all((scale >= 0) & (scale <= 1)):
            raise ValueError(f"MotionModel.translation_axis_scale must be 3 values in [0, 1], "
                             f"got {self.translation_axis_scale!r}")
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
        dt = rng.standard_normal((n, 3)) * (st * scale * np.asarray(self.translation_axis_scale))
        dw = rng.standard_normal((n, 3)) * (sr * scale)
        return particles.with_poses(perturb_about_origin(particles.poses, dt, dw))
