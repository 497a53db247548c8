"""Tests for mvtop_cli.eval.continuous: errors modulo a continuous symmetry are exact minima."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.eval import continuous as C
from mvtop_cli.eval import metrics as M

AXIS, POINT = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.025])
FLIP = C.rotation_about(np.array([1.0, 0.0, 0.0]), POINT, np.array(np.pi))


def _peg_points(rng):
    theta, z = rng.uniform(0, 2 * np.pi, 400), rng.uniform(0.0, 0.05, 400)
    return np.stack([0.004 * np.cos(theta), 0.004 * np.sin(theta), z], axis=1)


def test_a_turn_about_the_axis_scores_zero_at_any_angle():
    rng = np.random.default_rng(0)
    pts = _peg_points(rng)
    T_gt = np.tile(np.eye(4), (6, 1, 1))
    T_gt[:, :3, 3] = rng.normal(size=(6, 3))
    T_est = T_gt @ C.rotation_about(AXIS, POINT, rng.uniform(0, 2 * np.pi, 6)) @ FLIP
    G = np.stack([np.eye(4), FLIP])
    for f in (C.add, C.mssd, C.pose_error_bbox):
        np.testing.assert_allclose(f(T_est, T_gt, pts, G, AXIS, POINT), 0.0, atol=1e-9)
    np.testing.assert_allclose(C.closest_equivalent(T_est, T_gt, pts, G, AXIS, POINT), T_gt, atol=1e-9)


def test_minimum_matches_a_dense_search_and_beats_a_finite_list():
    corners = M.box_corners([-0.004, -0.004, 0.0], [0.004, 0.004, 0.05])
    T_gt = np.eye(4)[None]
    T_est = C.rotation_about(AXIS, POINT, np.array([0.4321]))
    T_est[:, :3, 3] += [0.0002, -0.0001, 0.0003]
    exact = C.pose_error_bbox(T_est, T_gt, corners, np.eye(4)[None], AXIS, POINT)[0]
    dense = C.rotation_about(AXIS, POINT, np.linspace(0, 2 * np.pi, 400001))
    brute = M.pose_error_bbox(T_est[0] @ dense, T_gt[0], corners).min()
    assert exact == pytest.approx(brute, abs=1e-9)
    # a pure turn about the axis: exactly 0, where the 1,000-element list (0.36 deg) leaves micrometres
    T_turn = C.rotation_about(AXIS, POINT, np.array([0.4321]))
    listed = C.rotation_about(AXIS, POINT, np.radians(np.arange(0, 360, 0.36)))
    assert C.pose_error_bbox(T_turn, T_gt, corners, np.eye(4)[None], AXIS, POINT)[0] < 1e-12
    assert M.pose_error_bbox(T_turn, T_gt, corners, listed)[0] > 5e-6


def test_closest_in_rotation_leaves_no_error_about_the_axis_and_beats_every_member():
    from mvtop_cli.geometry import se3

    rng = np.random.default_rng(4)
    G = np.stack([np.eye(4), FLIP])
    T_gt = np.tile(np.eye(4), (5, 1, 1))
    T_gt[:, :3, :3] = se3.rotvec_to_matrix(rng.normal(size=(5, 3)))
    tilt = se3.make_pose(se3.rotvec_to_matrix(np.radians([1.5, -0.7, 0.3])), [0.0002, 0.0, -0.0001])
    T_est = T_gt @ tilt @ C.rotation_about(AXIS, POINT, rng.uniform(0, 2 * np.pi, 5)) @ FLIP
    S = C.closest_in_rotation(T_est, T_gt, G, AXIS, POINT)
    T_sym = T_est @ S
    e = M.tangent_error(T_sym, T_gt)
    b = np.einsum("nij,j->ni", T_sym[:, :3, :3], AXIS)  # the axis of the equivalent, world axes
    np.testing.assert_allclose(np.einsum("ni,ni->n", e[:, 3:], b), 0.0, atol=1e-12)
    dense = C.rotation_about(AXIS, POINT, np.linspace(0, 2 * np.pi, 20001))
    for i in range(5):
        members = np.concatenate([T_est[i] @ dense @ g for g in G])
        best = se3.rotation_angle(T_gt[i, :3, :3], members[:, :3, :3]).min()
        assert se3.rotation_angle(T_gt[i, :3, :3], T_sym[i, :3, :3]) <= best + 1e-7
