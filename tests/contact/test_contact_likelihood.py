"""Contact likelihood (M-VTOP eq. 8-9) against hand-computed logistic values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvtop_cli.contact.likelihood import contact_likelihood, log_contact_likelihood, log_penetration_likelihood

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


def test_penetration_factor_against_hand_computed_logistic():
    tol, soft = 1e-4, 5e-5
    phi = np.array([1e-3, 0.0, -1e-4, -2e-4, -3e-3])
    # (φ + τ_p) / σ_p = 22, 2, 0, -2, -58
    expected = [-math.log1p(math.exp(-22)), -math.log1p(math.exp(-2)), math.log(0.5), -math.log1p(math.exp(2)),
                -58 - math.log1p(math.exp(-58))]
    np.testing.assert_allclose(log_penetration_likelihood(phi, tol, soft), expected, rtol=1e-12)
    deep = log_penetration_likelihood(np.array([-1e-2]), tol, soft)
    assert np.isfinite(deep).all() and deep[0] == pytest.approx(-(1e-2 - tol) / soft, rel=1e-9)
    with pytest.raises(ValueError, match="sigma_p"):
        log_penetration_likelihood(phi, tol, 0.0)


def test_penetration_factor_shapes_the_frame_likelihood_under_contact():
    """The estimator's likelihood under contact: a pose sunk 0.5 mm into the receptacle scores
    lower with the factor than without, by the factor's value; a pose on the surface the same."""
    import dataclasses
    from pathlib import Path

    from mvtop_cli.config import load_config
    from mvtop_cli.estimator.likelihood import Likelihood
    from mvtop_cli.estimator.observation import Observation
    from mvtop_cli.estimator.scene import SceneModel
    from mvtop_cli.records import Frame

    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "cube.yaml")
    cfg = dataclasses.replace(cfg, modalities=("contact",))
    scene = SceneModel(cfg)
    # poses found from the signed distance itself: lower a cube over the receptacle until phi crosses 0
    frame = Frame(0, 0, np.eye(4), contact=True)
    obs = Observation({}, {}, {}, {}, [], [], "none")
    heights = np.linspace(0.06, 0.0, 601)
    T = np.repeat(np.eye(4)[None], len(heights), axis=0)
    T[:, 2, 3] = heights
    phi = scene.phi(T)
    on = T[np.argmin(np.abs(phi))][None]
    sunk = on.copy()
    sunk[0, 2, 3] -= 5e-4
    with_f = Likelihood(cfg, scene, frame, obs, True, lambda name: 1.0)
    off = dataclasses.replace(cfg, contact=dataclasses.replace(cfg.contact, penetration_softness_m=None))
    without = Likelihood(off, scene, frame, obs, True, lambda name: 1.0)
    poses = np.concatenate([on, sunk])
    phis = scene.phi(poses)
    assert abs(phis[0]) < 1e-4 and phis[1] < -3e-4
    diff = with_f(poses) - without(poses)
    np.testing.assert_allclose(diff, log_penetration_likelihood(phis, cfg.contact.penetration_tolerance_m,
                                                                cfg.contact.penetration_softness_m), rtol=1e-9)
    assert diff[1] < -5.0 and diff[0] > -1.0
