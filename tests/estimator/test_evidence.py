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
    assert not report.pinned
    assert EvidenceReport({"front": 0.9}, 10.0, np.where(np.isinf(widths), 1e-3, widths)).pinned


def test_an_estimate_in_a_trough_reads_as_unpinned():
    """Where the log-likelihood rises on both sides (the estimate sits in a trough, not on a
    peak), the axis is not pinned: its width is inf."""
    T0 = np.eye(4)

    def bowl(T: np.ndarray) -> np.ndarray:  # a minimum, not a peak, along x
        return (T[:, 0, 3] / 1e-3) ** 2

    _, widths = likelihood_widths(bowl, T0, 5e-4, np.radians(0.5))
    assert np.isinf(widths[0])


def test_evidence_covariance_takes_the_prior_where_the_likelihood_is_flat_and_never_exceeds_it():
    from mvtop_cli.config import GraspPrior
    from mvtop_cli.estimator.evidence import evidence_covariance
    from mvtop_cli.estimator.prior import GraspPriorModel

    prior = GraspPriorModel(GraspPrior(translation_m=0.003, rotation_deg=10.0), 2.0).sigma
    np.testing.assert_allclose(prior, [0.003 / np.sqrt(3)] * 3 + [np.radians(10.0) / np.sqrt(3)] * 3)
    widths = np.array([2e-4, np.inf, 0.01, np.radians(0.3), np.radians(0.3), np.inf])
    cov = evidence_covariance(widths, prior)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [2e-4, prior[1], prior[2], np.radians(0.3), np.radians(0.3),
                                                       prior[5]])
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_evidence_covariance_scales_the_widths_by_the_factor_up_to_the_prior():
    from mvtop_cli.estimator.evidence import evidence_covariance

    prior = np.full(6, 1e-3)
    widths = np.array([1e-4, 2e-4, 5e-4, np.inf, 1e-4, 1e-4])
    sd = np.sqrt(np.diag(evidence_covariance(widths, prior, factor=3.0)))
    # 3 x the widths, the prior where the axis is flat or 3 x the width would exceed it
    np.testing.assert_allclose(sd, [3e-4, 6e-4, 1e-3, 1e-3, 3e-4, 3e-4])
    np.testing.assert_array_equal(evidence_covariance(widths, prior), evidence_covariance(widths, prior, 1.0))


def test_the_reported_covariance_adds_the_scaled_widths_to_the_particles():
    """`output.evidence_width_factor` changes the reported covariance by exactly the evidence term
    and leaves the estimate alone (the factor is a reading, not part of the filter)."""
    import dataclasses
    from pathlib import Path

    from mvtop_cli.config import load_config
    from mvtop_cli.estimator import Estimator
    from mvtop_cli.estimator.evidence import evidence_covariance
    from mvtop_cli.io.frames import FrameReader
    from mvtop_cli.io.mcap_reader import McapLog
    from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

    root = Path(__file__).resolve().parents[2]
    base = load_config(root / "configs" / "cube.yaml")
    base = dataclasses.replace(base, filter=dataclasses.replace(base.filter, num_particles=100))
    out = {}
    for factor in (1.0, 3.0):
        cfg = dataclasses.replace(base, output=dataclasses.replace(base.output, evidence_width_factor=factor))
        with McapLog(root / "sample_logs" / "cube.mcap") as log:
            reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
            est = Estimator.from_config(cfg, lambda fr, t, reader=reader: reader.tf.lookup("world", fr, t))
            for frame in reader:
                fe = est.step(frame)
                if frame.index == 2:
                    break
        out[factor] = (fe, est.prior.sigma)
    (a, prior), (b, _) = out[1.0], out[3.0]
    np.testing.assert_array_equal(a.T_ee_object, b.T_ee_object)
    sigma = a.evidence.likelihood_sigma
    assert np.isfinite(sigma).sum() >= 3  # the test means something only where the evidence pins axes
    expected = evidence_covariance(sigma, prior, 3.0) - evidence_covariance(sigma, prior, 1.0)
    np.testing.assert_allclose(b.covariance - a.covariance, expected, rtol=1e-9, atol=1e-18)
    assert np.trace(expected) > 0
