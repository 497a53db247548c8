"""Pinhole camera model in the OpenCV optical convention (x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of one camera or tactile sensor.

    ``K`` is the (3, 3) intrinsic matrix in pixels; ``width``/``height`` in pixels;
    ``distortion`` holds the CameraInfo ``D`` coefficients for ``distortion_model``
    (``plumb_bob`` or ``rational_polynomial``; empty or all-zero means none).
    """

    width: int
    height: int
    K: np.ndarray
    distortion_model: str = "plumb_bob"
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.abs(np.asarray(self.distortion)) > 0))

    @staticmethod
    def from_fov(width: int, height: int, fx: float, fy: float | None = None) -> "PinholeCamera":
        """Camera with the principal point at the image centre and focal lengths in pixels."""
        fy = fx if fy is None else fy
        K = np.array([[fx, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return PinholeCamera(width=width, height=height, K=K)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Project points (..., 3) in the optical frame [m] to pixels (..., 2), ignoring distortion."""
        p = np.asarray(p_cam, dtype=np.float64)
        z = p[..., 2]
        u = self.fx * p[..., 0] / z + self.cx
        v = self.fy * p[..., 1] / z + self.cy
        return np.stack([u, v], axis=-1)
