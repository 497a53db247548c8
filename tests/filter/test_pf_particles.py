"""ParticleSet: log-weight normalisation, ESS, mean and spread."""

import numpy as np
import pytest
from scipy.special import logsumexp

from mvtop_cli.filter.particles import ParticleSet, ess_from_log_weights, log_sum_exp, normalise_log_weights
from mvtop_cli.geometry import se3


def _random_poses(rng, n):
    return se3.exp_se3(rng.normal(scale=[0.01] * 3 + [0.3] * 3, size=(n, 6)))


def test_ess_of_known_weights():
    w = np.array([0.5, 0.25, 0.25])
    assert ess_from_log_weights(np.log(w)) == pytest.approx(1.0 / np.sum(w**2))
    assert ess_from_log_weights(np.log(w) + 123.4) == pytest.approx(8.0 / 3.0)
    assert ess_from_log_weights(np.zeros(7)) == pytest.approx(7.0)
    assert ess_from_log_weights(np.array([0.0, -np.inf, -np.inf])) == pytest.approx(1.0)


def test_ess_is_stable_for_extreme_log_weights():
    # exp() of these overflows / underflows in float64; the ESS must not.
    lw = np.array([1e5, 1e5, 1e5 - np.log(2.0), -1e5])
    w = np.array([1.0, 1.0, 0.5, 0.0])
    assert ess_from_log_weights(lw) == pytest.approx(w.sum() ** 2 / np.sum(w**2))


def test_normalise_rejects_unusable_weights():
    with pytest.raises(ValueError, match="NaN"):
        normalise_log_weights(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match=r"\+inf"):
        normalise_log_weights(np.array([0.0, np.inf]))
    with pytest.raises(ValueError, match="-inf"):
        normalise_log_weights(np.full(3, -np.inf))
    lw = normalise_log_weights(np.array([3.0, 3.0, -np.inf]))
    np.testing.assert_allclose(np.exp(lw), [0.5, 0.5, 0.0])


def test_particle_set_validates_and_is_read_only():
    rng = np.random.default_rng(0)
    poses = _random_poses(rng, 4)
    ps = ParticleSet.uniform(poses)
    assert len(ps) == 4
    np.testing.assert_allclose(ps.weights(), 0.25)
    with pytest.raises(ValueError):
        ps.poses[0, 0, 3] = 1.0
    poses[0, 0, 3] = 99.0  # the set holds its own copy
    assert ps.poses[0, 0, 3] != 99.0
    with pytest.raises(ValueError, match="shape"):
        ParticleSet(poses[:, :3], np.zeros(4))
    with pytest.raises(ValueError, match="shape"):
        ParticleSet(poses, np.zeros(3))
    with pytest.raises(ValueError):
        ParticleSet(poses, np.full(4, np.nan))


def test_mean_and_spread_use_se3_with_normalised_weights():
    rng = np.random.default_rng(1)
    poses = _random_poses(rng, 50)
    lw = rng.normal(size=50) * 3 + 500.0
    ps = ParticleSet(poses, lw)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    np.testing.assert_allclose(ps.weights(), w, rtol=1e-12)
    np.testing.assert_allclose(ps.mean(), se3.weighted_mean(poses, w), atol=1e-12)
    spread = ps.spread()
    mean, cov = se3.pose_spread(poses, w)
    np.testing.assert_allclose(spread.mean, mean, atol=1e-12)
    np.testing.assert_allclose(spread.covariance, cov, atol=1e-15)
    assert spread.translation_std_m == pytest.approx(np.sqrt(np.trace(cov[:3, :3]) / 3))
    assert spread.rotation_rms_rad == pytest.approx(np.sqrt(np.trace(cov[3:, 3:])))
    assert ps.ess() == pytest.approx(1.0 / np.sum(w**2))


def test_log_sum_exp_gives_scipys_bits():
    # The filter's weights, ESS and evidence must not move by a bit when scipy's logsumexp is
    # replaced: same value for spreads, ties at the maximum, -inf entries and edge cases.
    rng = np.random.default_rng(3)
    cases = [rng.normal(scale=sc, size=n) for sc in (1e-3, 1.0, 30.0, 3000.0) for n in (1, 2, 7, 500, 3000)]
    tied = rng.normal(size=400)
    tied[[5, 77, 301]] = tied.max() + 1.0
    dead = rng.normal(scale=50.0, size=300)
    dead[rng.random(300) < 0.4] = -np.inf
    cases += [tied, dead, np.full(5, -np.inf), np.array([np.inf, 0.0]), np.array([1e308, 1e308]),
              np.array([np.nan, 1.0]), np.array([-745.0, -746.0])]
    for a in cases:
        with np.errstate(all="ignore"):
            want = float(logsumexp(a))
        got = log_sum_exp(a)
        assert got == want or (np.isnan(got) and np.isnan(want)), (a[:4], got, want)
    assert log_sum_exp(np.array([])) == -np.inf
    assert log_sum_exp(np.log([1.0, 2.0, 3.0])) == pytest.approx(np.log(6.0), rel=1e-15)
