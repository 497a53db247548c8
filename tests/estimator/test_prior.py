"""The grasp prior's spread about an estimate (``GraspPriorModel.covariance_about``): what a
suspect frame reports."""

from __future__ import annotations

import numpy as np

from mvtop_cli.config import GraspPrior
from mvtop_cli.estimator.prior import GraspPriorModel
from mvtop_cli.estimator.symmetry import SymmetryFold
from mvtop_cli.geometry import se3


def _prior() -> GraspPriorModel:
    return GraspPriorModel(GraspPrior(translation_m=0.003, rotation_deg=10.0), 2.0)


def test_at_the_nominal_grasp_it_is_the_priors_covariance():
    prior = _prior()
    np.testing.assert_allclose(prior.covariance_about(prior.T_ee_object_nominal), np.diag(prior.sigma**2),
                               rtol=0, atol=1e-18)


def test_an_estimate_off_the_nominal_grasp_adds_its_offset_squared():
    prior = _prior()
    T_nom = prior.T_ee_object_nominal
    dt, dw = np.array([0.002, -0.001, 0.0005]), np.radians([0.0, 0.0, 25.0])
    T_est = se3.make_pose(se3.rotvec_to_matrix(dw) @ T_nom[:3, :3], T_nom[:3, 3] + dt)
    cov = prior.covariance_about(T_est)
    d = np.concatenate([-dt, -dw])  # the nominal's offset from the estimate
    np.testing.assert_allclose(cov, np.diag(prior.sigma**2) + np.outer(d, d), rtol=1e-9, atol=1e-15)
    # a truth drawn from the prior lies within the 95 % chi-square bound about the estimate about
    # as often as about the nominal grasp (the estimate 25 deg off: nearly never without the offset)
    rng = np.random.default_rng(0)
    truths = prior.sample(4000, rng).poses
    e = np.concatenate([truths[:, :3, 3] - T_est[:3, 3],
                        se3.matrix_to_rotvec(truths[:, :3, :3] @ T_est[:3, :3].T)], axis=1)
    nees = np.einsum("ni,ij,nj->n", e, np.linalg.inv(cov), e)
    nees_prior_only = np.einsum("ni,ij,nj->n", e, np.linalg.inv(np.diag(prior.sigma**2)), e)
    assert np.mean(nees <= 12.59) > 0.95
    assert np.mean(nees_prior_only <= 12.59) < 0.05


def test_a_symmetric_equivalent_counts_from_the_nearest_cell():
    # a part with a 90 deg turn about the ee z axis as a symmetry (in the object frame: the
    # nominal grasp turns the object 180 deg about x, so about the object's -z)
    prior = _prior()
    T_nom = prior.T_ee_object_nominal
    turn = np.eye(4)
    turn[:3, :3] = se3.rotvec_to_matrix(np.radians([0.0, 0.0, 90.0]))
    group = np.stack([np.linalg.matrix_power(turn, k) for k in range(4)])
    fold = SymmetryFold(group)
    small = se3.make_pose(se3.rotvec_to_matrix(np.radians([0.0, 3.0, 0.0])) @ T_nom[:3, :3], T_nom[:3, 3])
    np.testing.assert_allclose(prior.covariance_about(small @ turn, fold), prior.covariance_about(small),
                               rtol=1e-9, atol=1e-15)
    assert prior.covariance_about(small @ turn)[5, 5] > 2.0  # unfolded: a quarter turn, squared [rad^2]
