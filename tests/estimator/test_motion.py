"""Prior sampling and the motion model (Algorithm 4): spreads and the noise convention."""

import numpy as np
import pytest

from mvtop_cli.estimator.motion import MotionModel
from mvtop_cli.estimator.prior import init_from_prior, init_uniform_box
from mvtop_cli.filter.particles import ParticleSet
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.se3 import perturb_about_origin

# Nominal grasp: object +z = ee -z, object origin 20 mm ahead of the TCP (docs/frames.md).
T_NOMINAL = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.0])), [0.0, 0.0, 0.02])
# A generic nominal pose, so that ee axes and object axes differ.
T_TILTED = se3.make_pose(se3.rotvec_to_matrix(np.array([0.4, -0.7, 1.1])), [0.003, -0.002, 0.02])


def _offsets(poses, T0):
    """Per-particle (dt, dw) in ee axes with the module's convention."""
    dt = poses[:, :3, 3] - T0[:3, 3]
    dw = se3.matrix_to_rotvec(poses[:, :3, :3] @ T0[:3, :3].T)
    return dt, dw


def test_perturb_about_origin_rotates_about_the_object_origin_in_ee_axes():
    dw = np.array([0.0, 0.0, 0.3])
    T = perturb_about_origin(T_TILTED, np.zeros(3), dw)
    np.testing.assert_allclose(T[:3, 3], T_TILTED[:3, 3])  # no lever arm
    np.testing.assert_allclose(T[:3, :3], se3.rotvec_to_matrix(dw) @ T_TILTED[:3, :3], atol=1e-12)
    T = perturb_about_origin(T_TILTED, np.array([1e-3, 0, 0]), np.zeros(3))
    np.testing.assert_allclose(T[:3, 3] - T_TILTED[:3, 3], [1e-3, 0, 0], atol=1e-15)


@pytest.mark.parametrize("T0", [T_NOMINAL, T_TILTED])
def test_gaussian_prior_spread_matches_requested_sigmas(T0):
    rng = np.random.default_rng(3)
    st, sr = np.array([1e-3, 2e-3, 0.5e-3]), np.deg2rad([2.0, 5.0, 1.0])
    ps = init_from_prior(T0, st, sr, 20000, rng)
    assert isinstance(ps, ParticleSet) and len(ps) == 20000
    np.testing.assert_allclose(ps.weights(), 1.0 / 20000)
    dt, dw = _offsets(ps.poses, T0)
    # Per-axis sigmas are along the ee axes, whatever the nominal rotation.
    np.testing.assert_allclose(dt.std(axis=0), st, rtol=0.03)
    np.testing.assert_allclose(dw.std(axis=0), sr, rtol=0.03)
    np.testing.assert_allclose(dt.mean(axis=0), 0.0, atol=4 * st.max() / np.sqrt(20000))
    spread = ps.spread()
    np.testing.assert_allclose(np.sqrt(np.diag(spread.covariance)), np.r_[st, sr], rtol=0.03)


def test_isotropic_prior_reports_its_sigma_as_spread():
    rng = np.random.default_rng(4)
    ps = init_from_prior(T_NOMINAL, 1e-3, np.deg2rad(3.0), 20000, rng)
    spread = ps.spread()
    assert spread.translation_std_m == pytest.approx(1e-3, rel=0.03)
    assert spread.rotation_std_rad == pytest.approx(np.deg2rad(3.0), rel=0.03)
    assert spread.translation_rms_m == pytest.approx(np.sqrt(3) * 1e-3, rel=0.03)
    np.testing.assert_allclose(ps.mean()[:3, 3], T_NOMINAL[:3, 3], atol=5e-5)


def test_uniform_box_prior_stays_in_the_box():
    rng = np.random.default_rng(5)
    a, b = 3e-3, np.deg2rad(10.0)
    ps = init_uniform_box(T_TILTED, a, b, 20000, rng)
    dt, dw = _offsets(ps.poses, T_TILTED)
    assert np.all(np.abs(dt) <= a + 1e-15) and np.all(np.abs(dw) <= b + 1e-12)
    np.testing.assert_allclose(dt.std(axis=0), a / np.sqrt(3), rtol=0.03)
    np.testing.assert_allclose(dw.std(axis=0), b / np.sqrt(3), rtol=0.03)
    assert np.abs(dt).max() > 0.99 * a  # and fills it


@pytest.mark.parametrize("contact", [False, True])
def test_propagate_noise_matches_the_contact_sigmas(contact):
    model = MotionModel(
        sigma_low_translation_m=1e-4,
        sigma_low_rotation_rad=np.deg2rad(0.1),
        sigma_high_translation_m=1e-3,
        sigma_high_rotation_rad=np.deg2rad(2.0),
    )
    rng = np.random.default_rng(6)
    n = 20000
    before = ParticleSet(np.broadcast_to(T_TILTED, (n, 4, 4)), rng.normal(size=n))
    after = model.propagate(before, contact, rng)
    np.testing.assert_array_equal(after.log_weights, before.log_weights)
    dt, dw = _offsets(after.poses, T_TILTED)
    st, sr = (1e-3, np.deg2rad(2.0)) if contact else (1e-4, np.deg2rad(0.1))
    assert model.sigmas(contact) == (st, sr)
    np.testing.assert_allclose(dt.std(axis=0), st, rtol=0.03)
    np.testing.assert_allclose(dw.std(axis=0), sr, rtol=0.03)
    # Noise about the object origin in ee axes: rotations alone never move the origin.
    rot_only = MotionModel(0.0, 0.1, 0.0, 0.1).propagate(before, contact, rng)
    np.testing.assert_allclose(rot_only.poses[:, :3, 3], before.poses[:, :3, 3], atol=1e-15)
    # scale multiplies both sigmas
    scaled = model.propagate(before, contact, rng, scale=0.5)
    dt, dw = _offsets(scaled.poses, T_TILTED)
    np.testing.assert_allclose(dt.std(axis=0), 0.5 * st, rtol=0.03)
    np.testing.assert_allclose(dw.std(axis=0), 0.5 * sr, rtol=0.03)
    # translation_axis_scale narrows the translation noise per ee axis; rotations keep theirs
    axes = MotionModel(1e-4, np.deg2rad(0.1), 1e-3, np.deg2rad(2.0), translation_axis_scale=(0.25, 0.5, 1.0))
    assert axes.sigmas(contact) == (st, sr)
    dt, dw = _offsets(axes.propagate(before, contact, rng, scale=0.5).poses, T_TILTED)
    np.testing.assert_allclose(dt.std(axis=0), 0.5 * st * np.array([0.25, 0.5, 1.0]), rtol=0.03)
    np.testing.assert_allclose(dw.std(axis=0), 0.5 * sr, rtol=0.03)


def test_motion_model_rejects_bad_values():
    with pytest.raises(ValueError, match="sigma_high_rotation_rad"):
        MotionModel(0.0, 0.0, 0.0, -1.0)
    with pytest.raises(ValueError, match=r"translation_axis_scale must be 3 values in \[0, 1\]"):
        MotionModel(0.0, 0.0, 0.0, 0.0, translation_axis_scale=(1.0, -0.5, 1.0))
    with pytest.raises(ValueError, match=r"translation_axis_scale must be 3 values in \[0, 1\]"):
        MotionModel(0.0, 0.0, 0.0, 0.0, translation_axis_scale=(1.0, 1.0))
    with pytest.raises(ValueError, match=r"translation_axis_scale must be 3 values in \[0, 1\]"):
        MotionModel(0.0, 0.0, 0.0, 0.0, translation_axis_scale=(1.0, float("nan"), 1.0))
    model = MotionModel(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="contact"):
        model.sigmas(None)
    with pytest.raises(ValueError, match="sigma_translation_m"):
        init_from_prior(T_NOMINAL, -1.0, 0.1, 3, np.random.default_rng(0))


def test_priors_and_motion_are_deterministic_given_the_rng():
    model = MotionModel(1e-4, 1e-3, 1e-3, 1e-2)
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(42)
        ps = init_uniform_box(T_NOMINAL, 3e-3, 0.17, 100, rng)
        ps = model.propagate(init_from_prior(ps.mean(), 1e-3, 0.05, 100, rng), True, rng)
        runs.append(ps.poses)
    np.testing.assert_array_equal(runs[0], runs[1])
