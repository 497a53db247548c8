"""The evidence diagnostic's likelihood widths: a Gaussian log-likelihood's standard deviations
are read back per axis, a flat axis is ``inf``, and the report's summaries follow them."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.estimator.evidence import EvidenceReport, likelihood_widths
from mvtop_cli.geometry import se3


def _gaussian(T0: np.ndarray, sigma: np.ndarray):
    """log N(pose; T0, diag(sigma^2)) up to a constant, in the tangent convention of the prior
    (origin moved along ee axes, rotation vector in ee axes); ``inf`` sigma: flat."""
    def ll(T: np.ndarray) -> np.ndarray:
        dt = T[:, :3, 3] - T0[:3, 3]
        dw = se3.matrix_to_rotvec(T[:, :3, :3] @ T0[:3, :3].T)
        d = np.concatenate([dt, dw], axis=1)
        return -0.5 * np.sum((d / sigma) ** 2, axis=1) + 10.0
    return ll


def test_widths_of_a_gaussian_likelihood_are_its_standard_deviations():
    T0 = se3.make_pose(se3.rotvec_to_matrix(np.array([0.1, -0.2, 0.3])), np.array([0.01, 0.0, 0.05]))
    sigma = np.array([2e-4, 5e-4, 1e-3, np.radians(0.2), np.radians(1.0), np.radians(3.0)])
    centre, widths = likelihood_widths(_gaussian(T0, sigma), T0, 5e-4, np.radians(0.5))
    assert centre == pytest.approx(10.0)
    np.testing.assert_allclose(widths, sigma, rtol=1e-3)


def test_a_flat_axis_is_infinite_and_sets_the_widest_width():
    T0 = np.eye(4)
    sigma = np.array([3e-4, 3e-4, np.inf, np.radians(0.5), np.radians(0.5), np.radians(0.5)])
    _, widths = likelihood_widths(_gaussian(T0, sigma), T0, 5e-4, np.radians(0.5))
    assert np.isinf(widths[2]) and np.isfinite(widths[[0, 1, 3, 4, 5]]).all()
    report = EvidenceReport({"front": 0.9, "left": 0.7}, 10.0, widths)
    assert report.min_iou == 0.7
    assert np.isinf(report.sigma_translation_m)
    assert report.sigma_rotation_deg == pytest.approx(0.5, rel=1e-3)
    d = report.as_dict()
    assert d["likelihood_sigma_translation_m"][2] is None and d["min_iou"] == 0.7


def test_an_estimate_in_a_trough_reads_as_unpinned():
    """Where the log-likelihood rises on both sides (the estimate sits in a trough, not on a
    peak), the axis is not pinned: its width is inf."""
    T0 = np.eye(4)

    def bowl(T: np.ndarray) -> np.ndarray:  # a minimum, not a peak, along x
        return (T[:, 0, 3] / 1e-3) ** 2

    _, widths = likelihood_widths(bowl, T0, 5e-4, np.radians(0.5))
    assert np.isinf(widths[0])
