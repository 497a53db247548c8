"""Visuo-tactile log-score (eq. 1-2)."""

import numpy as np
import pytest

from mvtop_cli.filter.scoring import sensor_weights, visuo_tactile_log_score, visuo_tactile_score


def _direct(iou_t, iou_v, gamma, nu, tau):
    s = iou_t @ gamma + iou_v @ nu
    e = np.exp(s / tau)
    return e / e.sum()


def test_log_score_equals_a_direct_softmax():
    rng = np.random.default_rng(0)
    iou_t, iou_v = rng.random((6, 2)), rng.random((6, 3))
    gamma, nu = np.array([0.2, 0.3]), np.array([0.1, 0.2, 0.2])  # sums to 1 (eq. 2)
    out = visuo_tactile_log_score(iou_t, iou_v, gamma, nu, 0.05)
    assert out.shape == (6,)
    np.testing.assert_allclose(np.exp(out), _direct(iou_t, iou_v, gamma, nu, 0.05), rtol=1e-12)


def test_paper_default_weights_balance_the_modalities():
    rng = np.random.default_rng(1)
    iou_t, iou_v = rng.random((5, 2)), rng.random((5, 4))
    out = visuo_tactile_log_score(iou_t, iou_v, None, None, 0.1)
    # gamma_i = 1/N_T, nu_j = 1/N_V, rescaled to sum to one: each modality weighs 1/2.
    expected = _direct(iou_t, iou_v, np.full(2, 0.25), np.full(4, 0.125), 0.1)
    np.testing.assert_allclose(np.exp(out), expected, rtol=1e-12)
    g, v = sensor_weights([True, True], [True] * 4)
    np.testing.assert_allclose(g, 0.25)
    np.testing.assert_allclose(v, 0.125)


def test_log_score_is_stable_at_tiny_temperature():
    iou_t = np.array([[0.90, 0.80], [0.91, 0.80], [0.10, 0.05]])
    iou_v = np.array([[0.7], [0.7], [0.2]])
    tau = 1e-4
    out = visuo_tactile_log_score(iou_t, iou_v, None, None, tau)
    assert np.all(np.isfinite(out))
    s = iou_t @ np.array([0.25, 0.25]) + iou_v @ np.array([0.5])
    # Differences of log-scores are differences of s / tau, exactly as eq. 1 says.
    np.testing.assert_allclose(out - out[0], (s - s[0]) / tau, rtol=1e-9, atol=1e-6)
    assert np.exp(out).sum() == pytest.approx(1.0)
    # the best particle: log(1 / (1 + e^-(s1 - s0)/tau)), to full precision
    assert out[1] == pytest.approx(-np.log1p(np.exp(-(s[1] - s[0]) / tau)), rel=1e-9)


def test_missing_sensor_is_dropped_and_weights_renormalised():
    rng = np.random.default_rng(2)
    iou_t, iou_v = rng.random((8, 2)), rng.random((8, 2))
    missing = iou_t.copy()
    missing[:, 1] = np.nan  # tactile sensor 1 has no image in this frame
    gamma, nu = np.array([0.4, 0.1]), np.array([0.3, 0.2])
    out = visuo_tactile_log_score(missing, iou_v, gamma, nu, 0.02)
    kept = np.array([0.4, 0.0]) / 0.9, nu / 0.9  # remaining weights rescaled to sum to 1
    np.testing.assert_allclose(np.exp(out), _direct(iou_t, iou_v, *kept, 0.02), rtol=1e-12)
    # With the defaults the remaining tactile sensor carries the tactile half alone.
    out = visuo_tactile_log_score(missing, iou_v, None, None, 0.02)
    expected = _direct(iou_t, iou_v, np.array([0.5, 0.0]), np.array([0.25, 0.25]), 0.02)
    np.testing.assert_allclose(np.exp(out), expected, rtol=1e-12)
    # A whole modality missing: the other one gets all the weight.
    out = visuo_tactile_log_score(None, iou_v, None, None, 0.02)
    np.testing.assert_allclose(np.exp(out), _direct(np.zeros((8, 0)), iou_v, np.zeros(0), np.full(2, 0.5), 0.02))


def test_without_renormalising_each_sensor_keeps_its_share():
    """renormalise=False (the estimator's scoring): a sensor contributes gamma_i IoU_i
    whichever others are present, so a frame of tactile images alone scores like the
    tactile part of a full frame."""
    rng = np.random.default_rng(3)
    iou_t, iou_v = rng.random((8, 2)), rng.random((8, 2))
    gamma, nu = np.array([0.25, 0.25]), np.array([0.25, 0.25])
    full = visuo_tactile_score(iou_t, iou_v, gamma, nu, renormalise=False)
    np.testing.assert_allclose(full, iou_t @ gamma + iou_v @ nu, rtol=1e-12)
    np.testing.assert_allclose(full, visuo_tactile_score(iou_t, iou_v, gamma, nu), rtol=1e-12)  # sums to 1 already
    touch_only = visuo_tactile_score(iou_t, np.full((8, 2), np.nan), gamma, nu, renormalise=False)
    np.testing.assert_allclose(touch_only, iou_t @ gamma, rtol=1e-12)
    # renormalised, the same frame would count touch twice as much
    np.testing.assert_allclose(visuo_tactile_score(iou_t, np.full((8, 2), np.nan), gamma, nu), 2 * iou_t @ gamma, rtol=1e-12)
    g, v = sensor_weights([True, False], [True, True], gamma, nu, renormalise=False)
    np.testing.assert_allclose(g, [0.25, 0.0])
    np.testing.assert_allclose(v, [0.25, 0.25])


def test_frame_without_sensors_is_uninformative_and_partial_nan_scores_zero():
    iou = np.full((4, 2), np.nan)
    np.testing.assert_allclose(visuo_tactile_log_score(iou, None, None, None, 0.01), -np.log(4))
    iou_t = np.array([[0.5], [np.nan], [0.5]])
    out = visuo_tactile_log_score(iou_t, None, None, None, 0.1)
    np.testing.assert_allclose(np.exp(out), _direct(np.array([[0.5], [0.0], [0.5]]), np.zeros((3, 0)), np.ones(1), np.zeros(0), 0.1))


def test_log_score_rejects_bad_inputs():
    iou = np.zeros((3, 1))
    with pytest.raises(ValueError, match="temperature"):
        visuo_tactile_log_score(iou, None, None, None, 0.0)
    with pytest.raises(ValueError, match="rows"):
        visuo_tactile_log_score(iou, np.zeros((4, 1)), None, None, 0.1)
    with pytest.raises(ValueError, match="gamma"):
        visuo_tactile_log_score(iou, None, np.array([-1.0]), None, 0.1)
    with pytest.raises(ValueError, match="at least one"):
        visuo_tactile_log_score(None, None, None, None, 0.1)


def test_score_is_eq2_and_independent_of_the_other_particles():
    rng = np.random.default_rng(7)
    iou_t, iou_v = rng.random((8, 2)), rng.random((8, 2))
    iou_v[:, 1] = np.nan  # an absent camera: the others share its weight
    s = visuo_tactile_score(iou_t, iou_v)
    # defaults: 1/2 per modality over the sensors present -> 1/4 per tactile sensor, 1/2 for the camera
    np.testing.assert_allclose(s, 0.25 * iou_t.sum(axis=1) + 0.5 * iou_v[:, 0], rtol=1e-12)
    # scoring a subset gives the same values (unlike eq. 1's softmax over the batch) ...
    np.testing.assert_allclose(visuo_tactile_score(iou_t[:3], iou_v[:3]), s[:3], rtol=1e-12)
    # ... and the log-score is the same up to the batch's normalising constant
    log_s = visuo_tactile_log_score(iou_t, iou_v, None, None, 0.01)
    np.testing.assert_allclose(log_s - s / 0.01, (log_s - s / 0.01)[0], atol=1e-9)
