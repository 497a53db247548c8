"""Eq. 2's visuo-tactile score and its sensor weights (``estimator.likelihood``)."""

import numpy as np
import pytest

from mvtop_cli.estimator.likelihood import eq2_weights, scaled_weights, sensor_weights, visuo_tactile_score


def test_paper_default_weights_balance_the_modalities():
    rng = np.random.default_rng(1)
    iou_t, iou_v = rng.random((5, 2)), rng.random((5, 4))
    # gamma_i = 1/N_T, nu_j = 1/N_V, rescaled to sum to one: each modality weighs 1/2.
    np.testing.assert_allclose(visuo_tactile_score(iou_t, iou_v), iou_t @ np.full(2, 0.25) + iou_v @ np.full(4, 0.125),
                               rtol=1e-12)
    g, v = sensor_weights([True, True], [True] * 4)
    np.testing.assert_allclose(g, 0.25)
    np.testing.assert_allclose(v, 0.125)


def test_missing_sensor_is_dropped_and_weights_renormalised():
    rng = np.random.default_rng(2)
    iou_t, iou_v = rng.random((8, 2)), rng.random((8, 2))
    missing = iou_t.copy()
    missing[:, 1] = np.nan  # tactile sensor 1 has no image in this frame
    gamma, nu = np.array([0.4, 0.1]), np.array([0.3, 0.2])
    out = visuo_tactile_score(missing, iou_v, gamma, nu)
    np.testing.assert_allclose(out, (0.4 * iou_t[:, 0] + iou_v @ nu) / 0.9, rtol=1e-12)  # rescaled to sum to 1
    # With the defaults the remaining tactile sensor carries the tactile half alone.
    out = visuo_tactile_score(missing, iou_v)
    np.testing.assert_allclose(out, 0.5 * iou_t[:, 0] + 0.25 * iou_v.sum(axis=1), rtol=1e-12)
    # A whole modality missing: the other one gets all the weight.
    np.testing.assert_allclose(visuo_tactile_score(None, iou_v), 0.5 * iou_v.sum(axis=1), rtol=1e-12)


def test_without_renormalising_each_sensor_keeps_its_share():
    """renormalise=False (the likelihood's scoring): a sensor contributes gamma_i IoU_i
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
    np.testing.assert_allclose(visuo_tactile_score(iou_t, np.full((8, 2), np.nan), gamma, nu), 2 * iou_t @ gamma,
                               rtol=1e-12)
    g, v = sensor_weights([True, False], [True, True], gamma, nu, renormalise=False)
    np.testing.assert_allclose(g, [0.25, 0.0])
    np.testing.assert_allclose(v, [0.25, 0.25])


def test_frame_without_sensors_scores_zero_and_partial_nan_scores_zero():
    np.testing.assert_allclose(visuo_tactile_score(np.full((4, 2), np.nan), None), 0.0)
    out = visuo_tactile_score(np.array([[0.5], [np.nan], [0.5]]), None)
    np.testing.assert_allclose(out, [0.5, 0.0, 0.5])


def test_score_rejects_bad_inputs():
    iou = np.zeros((3, 1))
    with pytest.raises(ValueError, match="rows"):
        visuo_tactile_score(iou, np.zeros((4, 1)))
    with pytest.raises(ValueError, match="gamma"):
        visuo_tactile_score(iou, None, np.array([-1.0]), None)
    with pytest.raises(ValueError, match="at least one"):
        visuo_tactile_score(None, None)
    with pytest.raises(ValueError, match="infinite"):
        visuo_tactile_score(np.array([[np.inf]]), None)


def test_score_is_eq2_and_independent_of_the_other_particles():
    rng = np.random.default_rng(7)
    iou_t, iou_v = rng.random((8, 2)), rng.random((8, 2))
    iou_v[:, 1] = np.nan  # an absent camera: the others share its weight
    s = visuo_tactile_score(iou_t, iou_v)
    # defaults: 1/2 per modality over the sensors present -> 1/4 per tactile sensor, 1/2 for the camera
    np.testing.assert_allclose(s, 0.25 * iou_t.sum(axis=1) + 0.5 * iou_v[:, 0], rtol=1e-12)
    # scoring a subset gives the same values (unlike eq. 1's softmax over the batch)
    np.testing.assert_allclose(visuo_tactile_score(iou_t[:3], iou_v[:3]), s[:3], rtol=1e-12)


def test_eq2_weights_default_share_and_weight_zero():
    np.testing.assert_allclose(eq2_weights([None, None], 0.5), [0.25, 0.25])
    np.testing.assert_allclose(eq2_weights([0.0, None], 0.5), [0.0, 0.25])  # 0 switches a sensor off
    np.testing.assert_allclose(eq2_weights([0.3, None, None], 1.0), [0.3, 1 / 3, 1 / 3])
    assert eq2_weights([], 0.5).shape == (0,)


def test_scaled_weights_keep_the_modality_share():
    w = np.array([0.25, 0.25])
    assert scaled_weights(["a", "b"], w, lambda n: 1.0) is w
    out = scaled_weights(["a", "b"], w, lambda n: 0.01 if n == "a" else 1.0)
    np.testing.assert_allclose(out, [0.0025, 0.4975])
    assert out.sum() == pytest.approx(w.sum())
