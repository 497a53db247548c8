"""Contact likelihood (M-VTOP eq. 8-9) against hand-computed logistic values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvtop_cli.contact.likelihood import contact_likelihood, log_contact_likelihood

TAU = 1e-3  # margin τ_c [m]
SIGMA = 0.5e-3  # softness σ_d [m]


def test_values_match_hand_computed_logistic():
    phi = np.array([-1e-3, 0.0, 1e-3, 2e-3])
    # (τ - φ) / σ = 4, 2, 0, -2
    expected = [1 / (1 + math.exp(-4)), 1 / (1 + math.exp(-2)), 0.5, 1 / (1 + math.exp(2))]
    np.testing.assert_allclose(contact_likelihood(phi, True, TAU, SIGMA), expected, rtol=1e-12)
    np.testing.assert_allclose(
        log_contact_likelihood(phi, True, TAU, SIGMA), np.log(expected), rtol=1e-12
    )
    assert expected[1] == pytest.approx(0.8807970779778823)


def test_monotone_decreasing_in_phi():
    phi = np.linspace(-5e-3, 5e-3, 1001)
    z = contact_likelihood(phi, True, TAU, SIGMA)
    log_z = log_contact_likelihood(phi, True, TAU, SIGMA)
    assert np.all(np.diff(z) < 0)
    assert np.all(np.diff(log_z) < 0)
    assert np.all((z > 0) & (z < 1))


def test_no_contact_is_one_everywhere():
    phi = np.array([-1.0, -1e-3, 0.0, 1e-3, 1.0, np.inf])
    np.testing.assert_array_equal(contact_likelihood(phi, False, TAU, SIGMA), np.ones(6))
    np.testing.assert_array_equal(log_contact_likelihood(phi, False, TAU, SIGMA), np.zeros(6))


def test_log_variant_stable_far_from_contact():
    phi = np.array([-1.0, 1.0])  # ±1 m: (τ - φ) / σ = ±2000, where exp overflows
    log_z = log_contact_likelihood(phi, True, TAU, SIGMA)
    assert np.all(np.isfinite(log_z))
    # log σ(s) -> s for s -> -inf and -> -exp(-s) ~ 0 for s -> +inf
    assert log_z[1] == pytest.approx((TAU - 1.0) / SIGMA, rel=1e-12)
    assert log_z[0] == pytest.approx(0.0, abs=1e-300)
    # the plain likelihood underflows to 0 there, which is why the log form exists
    assert contact_likelihood(phi, True, TAU, SIGMA)[1] == 0.0


def test_log_is_log_of_likelihood():
    phi = np.random.default_rng(0).normal(0.0, 2e-3, 200)
    np.testing.assert_allclose(
        np.exp(log_contact_likelihood(phi, True, TAU, SIGMA)),
        contact_likelihood(phi, True, TAU, SIGMA),
        rtol=1e-12,
    )


def test_half_at_margin_and_shape_kept():
    phi = np.full((3, 4), TAU)
    z = contact_likelihood(phi, True, TAU, SIGMA)
    assert z.shape == (3, 4)
    np.testing.assert_allclose(z, 0.5)


@pytest.mark.parametrize("softness", [0.0, -1e-3])
def test_non_positive_softness_rejected(softness):
    with pytest.raises(ValueError, match="softness"):
        contact_likelihood(np.zeros(2), True, TAU, softness)
    with pytest.raises(ValueError, match="softness"):
        log_contact_likelihood(np.zeros(2), False, TAU, softness)
