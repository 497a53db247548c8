"""The belief folded modulo the object's symmetries (estimator/symmetry.py) and its use by the filter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import ContinuousSymmetry
from mvtop_cli.estimator.motion import MotionModel
from mvtop_cli.estimator.symmetry import SymmetryFold
from mvtop_cli.filter.particles import ParticleSet
from mvtop_cli.filter.pf import ParticleFilter
from mvtop_cli.geometry import se3

AXIS = np.array([0.0, 0.0, 1.0])
POINT = np.array([0.0, 0.0, 0.025])  # the middle of a 50 mm round peg on its axis
FLIP = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.0])), [0.0, 0.0, 0.05])  # end for end
T0 = se3.make_pose(se3.rotvec_to_matrix(np.array([3.0, 0.2, 0.1])), [0.01, 0.02, 0.03])


def about_axis(theta: np.ndarray, axis=AXIS, point=POINT) -> np.ndarray:
    R = se3.rotvec_to_matrix(np.asarray(theta)[:, None] * axis)
    C = np.zeros((len(theta), 4, 4))
    C[:, :3, :3], C[:, :3, 3], C[:, 3, 3] = R, point - R @ point, 1.0
    return C


def noisy(n: int, rng, sigma_t=1e-4, sigma_r_deg=0.2) -> np.ndarray:
    eye = np.broadcast_to(np.eye(4), (n, 4, 4))
    return se3.perturb_about_origin(eye, rng.normal(0, sigma_t, (n, 3)), rng.normal(0, np.radians(sigma_r_deg), (n, 3)))


def round_peg_belief(n: int, seed: int) -> np.ndarray:
    """Poses near T0, each turned by a random angle about the axis, every other one flipped."""
    rng = np.random.default_rng(seed)
    P = noisy(n, rng) @ T0 @ about_axis(rng.uniform(-np.pi, np.pi, n))
    P[::2] = P[::2] @ FLIP
    return P


def test_a_belief_spread_about_the_axis_folds_to_its_identifiable_spread():
    fold = SymmetryFold(np.stack([np.eye(4), FLIP]), AXIS, POINT)
    ps = ParticleSet.uniform(round_peg_belief(2000, 0))
    plain, folded = ps.spread(), ps.spread(fold)
    assert np.degrees(plain.rotation_std_rad) > 30.0  # free about the axis and flipped: meaningless
    # the noise put in: 0.2 deg per axis, of which the two tilts remain (rms over 3 axes: 0.2 * sqrt(2/3))
    assert np.degrees(folded.rotation_std_rad) == pytest.approx(0.2 * np.sqrt(2 / 3), rel=0.1)
    R_mean = folded.mean[:3, :3]
    b = R_mean @ AXIS  # the axis in ee axes: no spread about it is left
    assert b @ folded.covariance[3:, 3:] @ b < (np.radians(0.01)) ** 2
    # the folded mean is a member of T0's class, up to the noise's standard error
    member = fold(folded.mean[None], T0)[0]
    assert np.linalg.norm(member[:3, 3] - T0[:3, 3]) < 2e-5
    assert np.degrees(se3.rotation_angle(member[:3, :3], T0[:3, :3])) < 0.02


def test_the_fold_picks_the_member_closest_to_the_reference():
    rng = np.random.default_rng(1)
    G = np.stack([np.eye(4), FLIP])
    axis = np.array([0.3, -0.2, 0.9])
    point = np.array([0.001, 0.002, 0.01])
    fold = SymmetryFold(G, axis, point)
    poses = round_peg_belief(20, 2) @ about_axis(rng.uniform(-3, 3, 20), axis / np.linalg.norm(axis), point)
    ref = se3.make_pose(se3.rotvec_to_matrix(np.array([2.9, 0.3, 0.0])), [0.0, 0.0, 0.0])
    out = fold(poses, ref)
    grid = np.linspace(-np.pi, np.pi, 3601)
    C = about_axis(grid, axis / np.linalg.norm(axis), point)
    for T, F in zip(poses, out, strict=True):
        members = np.concatenate([T @ g @ C for g in G])
        angles = se3.rotation_angle(ref[:3, :3], members[:, :3, :3])
        # same class: F is one of T's members (up to the grid's 0.1 deg step)
        assert np.min(np.linalg.norm((members - F).reshape(len(members), -1), axis=1)) < 3e-3
        # and no member is closer to the reference than F
        assert se3.rotation_angle(ref[:3, :3], F[:3, :3]) <= angles.min() + 1e-9


def test_a_discrete_fold_leaves_a_belief_inside_one_cell_exactly_as_it_was():
    rng = np.random.default_rng(3)
    quarter = se3.make_pose(se3.rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2])), [0.0, 0.0, 0.0])
    G = np.stack([np.eye(4), quarter, quarter @ quarter, quarter @ quarter @ quarter])
    fold = SymmetryFold(G)
    P = noisy(300, rng, sigma_r_deg=5.0) @ T0
    assert np.array_equal(fold(P, T0), P)
    ps = ParticleSet.uniform(P)
    assert np.array_equal(ps.spread(fold).covariance, ps.spread().covariance)
    # particles turned by a symmetry come back to the reference's cell
    turned = P.copy()
    turned[::3] = P[::3] @ G[rng.integers(1, 4, len(P[::3]))]
    np.testing.assert_allclose(fold(turned, T0), P, atol=1e-12)


def test_the_jump_check_compares_the_estimate_with_its_equivalent_closest_to_the_previous_mean():
    fold = SymmetryFold(np.stack([np.eye(4), FLIP]), AXIS, POINT)
    motion = MotionModel(1e-4, np.radians(0.1), 1e-4, np.radians(0.25))
    ps = ParticleSet.uniform(round_peg_belief(500, 4))
    estimate = ps.spread(fold).mean @ about_axis(np.array([1.2]))[0] @ FLIP  # the same pose, turned and flipped
    plain = ParticleFilter(motion, rng=np.random.default_rng(0))
    folding = ParticleFilter(motion, rng=np.random.default_rng(0), fold=fold)
    assert plain.check_jump(ps.spread(fold), estimate, False).jumped
    check = folding.check_jump(ps.spread(fold), estimate, False)
    assert not check.jumped and check.rotation_rad < 1e-6 and check.translation_m < 1e-12  # arccos rounding


def test_refine_keeps_a_round_peg_belief_in_one_chart():
    """With the fold, ``refine`` on a belief spread about the axis returns particles folded onto
    one representative (inside the tangent chart) and the estimate of the folded set."""
    fold = SymmetryFold(np.stack([np.eye(4), FLIP]), AXIS, POINT)
    motion = MotionModel(1e-4, np.radians(0.1), 1e-4, np.radians(0.25))
    pf = ParticleFilter(motion, rng=np.random.default_rng(5), refine_iterations=4, fold=fold)
    ps = ParticleSet.uniform(round_peg_belief(400, 6))

    def flat(T: np.ndarray) -> np.ndarray:  # a likelihood that cannot tell the members apart
        return np.zeros(len(T))

    result = pf.refine(ps, flat)
    R_mean = result.estimate[:3, :3]
    angles = se3.rotation_angle(R_mean, result.particles.poses[:, :3, :3])
    assert np.degrees(np.max(angles)) < 5.0  # one representative each, near the mean (no wrap around the axis)
    member = fold(result.estimate[None], T0)[0]
    assert np.degrees(se3.rotation_angle(member[:3, :3], T0[:3, :3])) < 0.2


def test_from_config_follows_the_object_and_the_switch():
    from dataclasses import replace

    from mvtop_cli.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "cube.yaml")
    scene_group = np.stack([np.eye(4)] + [s.matrix() for s in cfg.object.symmetries])
    assert isinstance(SymmetryFold.from_config(cfg, scene_group), SymmetryFold)
    off = replace(cfg, filter=replace(cfg.filter, fold_symmetries=False))
    assert SymmetryFold.from_config(off, scene_group) is None
    none = replace(cfg, object=replace(cfg.object, symmetries=()))
    assert SymmetryFold.from_config(none, np.eye(4)[None]) is None
    cont = replace(none, object=replace(none.object, continuous_symmetry=ContinuousSymmetry((0, 0, 2), (0, 0, 0.01))))
    fold = SymmetryFold.from_config(cont, np.eye(4)[None])
    assert fold is not None and fold.continuous and np.allclose(fold.axis, [0, 0, 1])
