"""Resampling schemes: registry, unbiasedness, systematic count bounds, zero weights."""

import numpy as np
import pytest

from mvtop_cli.filter.particles import ParticleSet
from mvtop_cli.filter.resampling import (
    available_schemes,
    get_scheme,
    resample,
    resample_if_needed,
)
from mvtop_cli.geometry import se3

SCHEMES = ("systematic", "stratified", "multinomial", "residual")


def _weights(rng, n):
    w = rng.gamma(0.5, size=n)
    w[rng.random(n) < 0.2] = 0.0
    w[0] = 0.0  # a leading and a trailing zero weight
    w[-1] = 0.0
    return w / w.sum()


def _log(w):
    with np.errstate(divide="ignore"):
        return np.log(w)  # zero weights -> -inf


def test_registry_lists_the_four_schemes_and_suggests_names():
    assert set(SCHEMES) <= set(available_schemes())
    with pytest.raises(ValueError, match="did you mean 'systematic'"):
        get_scheme("systematc")


@pytest.mark.parametrize("name", SCHEMES)
def test_schemes_are_unbiased(name):
    rng = np.random.default_rng(7)
    n, reps = 40, 2500
    w = _weights(rng, n)
    lw = _log(w) + 250.0  # unnormalised and shifted
    scheme = get_scheme(name)
    counts = np.zeros(n)
    for _ in range(reps):
        idx = scheme(lw, n, rng)
        assert idx.shape == (n,) and idx.dtype.kind == "i"
        counts += np.bincount(idx, minlength=n)
    mean = counts / reps
    # Each scheme's count variance is at most the multinomial one (systematic: <= 1/4).
    sd = np.sqrt(np.maximum(n * w * (1 - w), 0.25) / reps)
    assert np.all(np.abs(mean - n * w) <= 5 * sd), np.max(np.abs(mean - n * w) / sd)
    assert np.all(counts[w == 0] == 0)


def test_systematic_counts_are_floor_or_ceil_of_expected():
    for seed in range(200):
        rng = np.random.default_rng(seed)
        w = _weights(rng, 25)
        n_out = 25 + seed % 17
        counts = np.bincount(get_scheme("systematic")(_log(w), n_out, rng), minlength=25)
        expected = n_out * w
        assert counts.sum() == n_out
        assert np.all(counts >= np.floor(expected - 1e-9))
        assert np.all(counts <= np.ceil(expected + 1e-9))


@pytest.mark.parametrize("name", SCHEMES)
def test_schemes_handle_other_output_sizes_and_a_single_survivor(name):
    rng = np.random.default_rng(8)
    scheme = get_scheme(name)
    lw = np.array([-np.inf, -np.inf, 5.0, -np.inf])
    np.testing.assert_array_equal(scheme(lw, 9, rng), np.full(9, 2))
    idx = scheme(np.log(np.array([0.2, 0.3, 0.5])), 1000, rng)
    assert idx.shape == (1000,)
    np.testing.assert_allclose(np.bincount(idx) / 1000, [0.2, 0.3, 0.5], atol=0.06)


def test_resample_if_needed_follows_the_ess_threshold():
    rng = np.random.default_rng(9)
    poses = se3.exp_se3(rng.normal(scale=0.01, size=(10, 6)))
    lw = np.log(np.array([0.91] + [0.01] * 9))  # ESS ~ 1.2
    ps = ParticleSet(poses, lw)
    same, resampled = resample_if_needed(ps, 0.1, "systematic", rng)
    assert not resampled and same is ps
    out, resampled = resample_if_needed(ps, 0.5, "systematic", rng)
    assert resampled and len(out) == 10
    np.testing.assert_allclose(out.weights(), 0.1)
    assert np.sum(np.all(out.poses == poses[0], axis=(1, 2))) == 9  # floor/ceil of 9.1
    with pytest.raises(ValueError, match="unknown resampling scheme"):
        resample_if_needed(ps, 0.1, "nope", rng)
    with pytest.raises(ValueError, match="ess_threshold_fraction"):
        resample_if_needed(ps, 1.5, "systematic", rng)
    assert len(resample(ps, "residual", rng, n_out=4)) == 4


@pytest.mark.parametrize("name", SCHEMES)
def test_schemes_are_deterministic_given_the_rng(name):
    lw = _log(_weights(np.random.default_rng(10), 30))
    a = get_scheme(name)(lw, 30, np.random.default_rng(5))
    b = get_scheme(name)(lw, 30, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
