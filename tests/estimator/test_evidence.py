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


def test_an_axis_the_profile_leaves_open_is_not_pinned():
    """The probe pins every axis, the profile finds a pose as good as the estimate along x: the
    report's widths take the profile's, and the axis is open."""
    probe = np.array([1e-4, 1e-4, 1e-4, 0.005, 0.005, 0.005])
    profile = np.array([np.inf, 2e-4, 5e-5, 0.004, 0.01, 0.002])
    report = EvidenceReport({"left": 0.98}, 10.0, probe, profile)
    assert not report.pinned
    np.testing.assert_array_equal(report.widths, np.maximum(probe, profile))
    assert report.sigma_translation_m == pytest.approx(1e-4)  # the probe's own reading is unchanged
    assert EvidenceReport({"left": 0.98}, 10.0, probe, np.where(np.isinf(profile), 1e-3, profile)).pinned
    assert EvidenceReport({"left": 0.98}, 10.0, probe).pinned


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


def _quadratic(T0: np.ndarray, precision: np.ndarray):
    """-1/2 d' P d + 10 for the tangent offset d (6,) of each pose from ``T0``, as ``_gaussian``."""
    def ll(T: np.ndarray) -> np.ndarray:
        dt = T[:, :3, 3] - T0[:3, 3]
        dw = se3.matrix_to_rotvec(T[:, :3, :3] @ T0[:3, :3].T)
        d = np.concatenate([dt, dw], axis=1)
        return -0.5 * np.einsum("ni,ij,nj->n", d, precision, d) + 10.0
    return ll


def _profile(ll, T0, rng_seed=0):
    from mvtop_cli.estimator.evidence import profile_widths

    return profile_widths(ll, T0, float(ll(T0[None])[0]), 2e-3, np.radians(4.0), 2.5e-4, np.radians(0.25),
                          np.random.default_rng(rng_seed), 48, 5, 0.1)


def test_the_profile_reads_an_oblique_ridge_that_the_axis_probe_misses():
    """A likelihood flat along a ridge that slides along x while turning about x (a part sliding
    along an axis the pads cannot see): the probe's x width is the ridge's narrow cross-section,
    the profile's is the marginal width along x, sqrt(Sigma_xx) of the Gaussian."""
    T0 = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.1])), np.array([0.0, 0.0, 0.0125]))
    r = np.array([1e-3, 0.0, 0.0, 1.4e-3, 0.0, 0.0])
    r /= np.linalg.norm(r)
    s_par, s_perp = 2e-3, 2e-4
    precision = (np.eye(6) - np.outer(r, r)) / s_perp**2 + np.outer(r, r) / s_par**2
    marginal = np.sqrt(np.diag(np.linalg.inv(precision)))
    ll = _quadratic(T0, precision)
    _, probe = likelihood_widths(ll, T0, 5e-4, np.radians(0.5))
    profile = _profile(ll, T0)
    assert probe[0] < 0.4 * marginal[0]  # the probe sees the cross-section: 0.25 mm against 1.16 mm
    assert profile[0] == pytest.approx(marginal[0], rel=0.25)
    # axes off the ridge read their width; rx's marginal (0.09 deg) is below the profile's reach
    # (offsets of 1-4 deg: x would have to follow by 12-50 mm), so there it reads as the probe does
    np.testing.assert_allclose(profile[[1, 2, 4, 5]], marginal[[1, 2, 4, 5]], rtol=0.25)
    assert np.all(profile >= 0.9 * probe)
    report = EvidenceReport({"left": 0.99}, 10.0, probe, profile)
    np.testing.assert_array_equal(report.widths, np.maximum(probe, profile))
    assert report.as_dict()["profile_sigma_translation_m"][0] == pytest.approx(profile[0])
    assert "profile_sigma_translation_m" not in EvidenceReport({"left": 0.99}, 10.0, probe).as_dict()


def test_the_profile_of_a_gaussian_without_a_ridge_is_its_standard_deviations_and_is_seeded():
    T0 = np.eye(4)
    sigma = np.array([2e-4, 5e-4, 1e-3, np.radians(0.2), np.radians(1.0), np.radians(3.0)])
    ll = _gaussian(T0, sigma)
    profile = _profile(ll, T0)
    # axis-aligned: the pure axis step of the first round is each search's best, exactly the width
    np.testing.assert_allclose(profile, sigma, rtol=1e-6)
    T1 = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.1])), np.array([0.0, 0.0, 0.0125]))
    r = np.array([1e-3, 0.0, 0.0, 1.4e-3, 0.0, 0.0]) / np.hypot(1e-3, 1.4e-3)
    ridge = _quadratic(T1, (np.eye(6) - np.outer(r, r)) / 2e-4**2 + np.outer(r, r) / 2e-3**2)
    np.testing.assert_array_equal(_profile(ridge, T1), _profile(ridge, T1))  # same seed, same widths


def test_a_profile_that_finds_a_pose_as_good_as_the_estimate_leaves_the_axis_open():
    """A second peak 2 mm along y that scores as high as the estimate: the profile reaches it,
    so y is open (inf) although the probe reads a narrow peak there."""
    T0 = np.eye(4)
    sigma = np.full(6, 2e-4)
    near, far = _gaussian(T0, sigma), _gaussian(se3.make_pose(np.eye(3), np.array([0.0, 2e-3, 0.0])), sigma)

    def two_peaks(T: np.ndarray) -> np.ndarray:
        return np.maximum(near(T), far(T) + 0.5)

    _, probe = likelihood_widths(two_peaks, T0, 5e-4, np.radians(0.5))
    profile = _profile(two_peaks, T0)
    assert np.isfinite(probe[1]) and np.isinf(profile[1])
    assert np.isfinite(profile[[0, 2]]).all()


def test_the_profile_widens_the_reported_covariance_from_the_check_frame_on_and_leaves_the_estimates():
    """`output.evidence_profile` on the cube sample: the estimates are those of a run without it
    (the profile draws from a generator of its own), no frame before the first check carries a
    profile, and from that check (frame 9, `search.rival_every` 10) on the covariance holds the
    wider of the probe's and the profile's widths, carried to the next frames and to a resumed
    estimator."""
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
    assert base.search.rival_every == 10 and base.output.evidence_profile == "without_cameras"
    runs = {}
    for on in (False, True):
        cfg = dataclasses.replace(base, output=dataclasses.replace(base.output, evidence_profile=on))
        with McapLog(root / "sample_logs" / "cube.mcap") as log:
            reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
            est = Estimator.from_config(cfg, lambda fr, t, reader=reader: reader.tf.lookup("world", fr, t))
            runs[on] = [est.step(frame) for frame, _ in zip(reader, range(11))]
        runs[on, "prior"] = est.prior.sigma
    off, on, prior = runs[False], runs[True], runs[True, "prior"]
    for a, b in zip(off, on):
        np.testing.assert_array_equal(a.T_ee_object, b.T_ee_object)
        assert a.evidence.profile_sigma is None
    assert all(b.evidence.profile_sigma is None for b in on[:9])
    np.testing.assert_array_equal(on[9].evidence.profile_sigma, on[10].evidence.profile_sigma)
    for k in (9, 10):
        assert "suspect_estimate" not in on[k].flags  # else both report the prior's spread
        e = on[k].evidence
        expected = (evidence_covariance(e.widths, prior, base.output.evidence_width_factor)
                    - evidence_covariance(e.likelihood_sigma, prior, base.output.evidence_width_factor))
        np.testing.assert_allclose(on[k].covariance - off[k].covariance, expected, rtol=1e-9, atol=1e-18)
        assert np.all(np.diag(on[k].covariance) >= np.diag(off[k].covariance))
    assert np.any(on[9].evidence.profile_sigma > on[9].evidence.likelihood_sigma)  # the profile reads wider somewhere

    resumed = Estimator.from_config(dataclasses.replace(base, output=dataclasses.replace(
        base.output, evidence_profile=True)))
    resumed.resume_after(on[10])
    np.testing.assert_array_equal(resumed.profile_sigma, on[9].evidence.profile_sigma)
    # a frame without evidence (no sensor, no contact term) still carries the check's widths over
    resumed = Estimator.from_config(dataclasses.replace(base, output=dataclasses.replace(
        base.output, evidence_profile=True)))
    resumed.resume_after(dataclasses.replace(on[10], evidence=None))
    np.testing.assert_array_equal(resumed.profile_sigma, on[9].evidence.profile_sigma)


def test_by_default_the_profile_is_measured_where_no_camera_evidence_enters():
    """`output.evidence_profile: without_cameras` (the default) on the cube sample: touch alone (the
    M-TOP modalities) measures the profile on the check frame (9) and carries it on; with the
    cameras it is not measured, as with the setting off, and a check frame the cameras see drops
    widths an earlier check without them measured (here put in place before frame 9)."""
    import dataclasses
    from pathlib import Path

    from mvtop_cli.config import load_config
    from mvtop_cli.estimator import Estimator
    from mvtop_cli.io.frames import FrameReader
    from mvtop_cli.io.mcap_reader import McapLog
    from mvtop_cli.pipelines.estimate import log_topics, sensor_topics

    root = Path(__file__).resolve().parents[2]
    base = load_config(root / "configs" / "cube.yaml")
    base = dataclasses.replace(base, filter=dataclasses.replace(base.filter, num_particles=100))
    profiled = {}
    for modalities in (("tactile", "contact"), ("vision", "tactile", "contact")):
        cfg = dataclasses.replace(base, modalities=modalities)
        with McapLog(root / "sample_logs" / "cube.mcap") as log:
            reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
            est = Estimator.from_config(cfg, lambda fr, t, reader=reader: reader.tf.lookup("world", fr, t))
            frames = []
            for frame, _ in zip(reader, range(11)):
                if frame.index == 9 and "vision" in modalities:
                    est.profile_sigma = np.full(6, 1e-3)
                frames.append(est.step(frame))
        assert all(f.evidence is not None for f in frames)
        profiled[modalities] = [f.evidence.profile_sigma is not None for f in frames]
        assert (est.profile_sigma is not None) == ("vision" not in modalities)
    assert profiled["tactile", "contact"] == [False] * 9 + [True, True]
    assert profiled["vision", "tactile", "contact"] == [False] * 11


def test_leave_one_out_finds_the_pose_all_sensors_but_one_prefer():
    """Three sensors, four scored poses: sensors 1 and 2 prefer pose 3 to the estimate by 6 nats
    each, sensor 0 alone prefers the estimate by 20; poses 0 and 1 lie in the estimate's mode
    and are not candidates."""
    from mvtop_cli.estimator.evidence import leave_one_out

    terms_est = np.array([30.0, 10.0, 10.0])
    terms = np.array([[30.0, 10.0, 10.0],   # the estimate's mode
                      [29.0, 30.0, 30.0],   # better for everyone, but in the estimate's mode
                      [10.0, 11.0, 11.0],
                      [10.0, 16.0, 16.0]])
    ll = terms.sum(axis=1) - 1.0  # plus a contact term of -1 nat everywhere
    gains, rows = leave_one_out(terms, ll, np.array([False, False, True, True]), terms_est, terms_est.sum() - 1.0)
    np.testing.assert_allclose(gains, [12.0, -14.0, -14.0])  # without 0: 32 - 20; without 1 or 2: 25 - 39
    np.testing.assert_array_equal(rows, [3, 3, 3])
    none, where = leave_one_out(terms, ll, np.zeros(4, bool), terms_est, terms_est.sum() - 1.0)
    assert np.all(np.isneginf(none)) and np.all(where == -1)
    ll[3] = -np.inf  # a pose outside what the likelihood allows is no candidate
    gains, rows = leave_one_out(terms, ll, np.array([False, False, True, True]), terms_est, terms_est.sum() - 1.0)
    np.testing.assert_allclose(gains, [2.0, -19.0, -19.0])  # without 0: 22 - 20; without 1 or 2: 20 - 39
    np.testing.assert_array_equal(rows, [2, 2, 2])
