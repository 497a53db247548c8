"""Failure modes of the filter, provoked with real likelihoods: degenerate weights, ESS
collapse and its recovery, estimate jumps, the sensor consistency watch, and their reports."""

import numpy as np
import pytest

from mvtop_cli.estimator.motion import MotionModel
from mvtop_cli.estimator.prior import init_from_prior, init_uniform_box
from mvtop_cli.filter.health import (
    RivalMode,
    SensorConsistency,
    check_jump,
    count_warnings,
    jump_warning,
    step_warnings,
    suspect_warning,
    warning_lines,
)
from mvtop_cli.filter.pf import ParticleFilter
from mvtop_cli.geometry import se3
from mvtop_cli.geometry.se3 import perturb_about_origin

T_NOMINAL = se3.make_pose(se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.0])), [0.0, 0.0, 0.02])
FIRM = MotionModel(1e-5, np.deg2rad(0.01), 1e-4, np.deg2rad(0.1))


def _peak(T_true, width_m=3e-3, width_rad=np.deg2rad(10.0), tau=0.002):
    """An IoU-like score (1 at ``T_true``, falling off over mm and degrees) over a temperature."""

    def log_likelihood(T):
        dt = np.linalg.norm(T[:, :3, 3] - T_true[:3, 3], axis=1)
        angle = se3.rotation_angle(T[:, :3, :3], T_true[:3, :3])
        return np.exp(-((dt / width_m) ** 2) - (angle / width_rad) ** 2) / tau

    return log_likelihood


def _errors(T, T_true):
    return (float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]) * 1e3),
            float(np.rad2deg(se3.rotation_angle(T[:3, :3], T_true[:3, :3]))))


def _unique(poses):
    return len(np.unique(np.round(poses[:, :3, 3], 12), axis=0))


# -- 1. every weight zero or non-finite ---------------------------------------------------


@pytest.mark.parametrize("iterations", [0, 4])
def test_all_nan_likelihood_skips_the_update_and_never_yields_nan(iterations):
    rng = np.random.default_rng(1)
    prior = init_from_prior(T_NOMINAL, 5e-4, np.deg2rad(1.0), 200, rng)
    pf = ParticleFilter(FIRM, "systematic", 0.5, rng, refine_iterations=iterations, collapse_retry_iterations=24)
    result = pf.step(prior, False, lambda T: np.full(len(T), np.nan))
    assert "degenerate_weights" in result.flags
    assert np.all(np.isfinite(result.particles.poses)) and np.all(np.isfinite(result.estimate))
    assert np.all(np.isfinite(result.spread.covariance))
    # recovery: the predicted particles carried on (the motion model's noise widens them), unweighted by the frame
    assert result.spread.translation_rms_m >= prior.spread().translation_rms_m
    records = step_warnings(7, result.diagnostics, 200)
    assert [r["kind"] for r in records] == ["degenerate_weights"]
    assert records[0]["frame"] == 7 and records[0]["invalid"] == 200
    assert "the update was skipped" in records[0]["detail"]
    # the next frame, with a valid likelihood again, updates normally
    T_true = perturb_about_origin(T_NOMINAL, np.array([2e-4, 0, 0]), np.zeros(3))
    after = pf.step(result.particles, False, _peak(T_true, tau=0.05))
    assert "degenerate_weights" not in after.flags
    assert step_warnings(8, after.diagnostics, 200) == []


def test_some_nan_values_are_reported_as_invalid_not_degenerate():
    rng = np.random.default_rng(2)
    prior = init_from_prior(T_NOMINAL, 5e-4, np.deg2rad(1.0), 100, rng)
    base = _peak(T_NOMINAL)

    def holes(T):
        out = base(T)
        out[::4] = np.nan  # a degenerate render for a quarter of the poses
        return out

    result = ParticleFilter(FIRM, "systematic", 0.5, rng).update(prior, holes)
    assert result.flags == ()
    (record,) = step_warnings(0, result.diagnostics, 100)
    assert record["kind"] == "invalid_likelihood" and record["invalid"] == 25 and record["evaluated"] == 100


# -- 2. effective sample size collapse ----------------------------------------------------


def test_ess_collapse_is_redone_with_more_tempering_and_recovers():
    """One tempering stage on a likelihood far sharper than the prior puts all the weight on
    a particle or two; the retry's smaller stages and Metropolis moves restore the set."""
    truth_rng = np.random.default_rng(3)
    T_true = perturb_about_origin(
        T_NOMINAL, truth_rng.uniform(-1e-3, 1e-3, 3), truth_rng.uniform(-1, 1, 3) * np.deg2rad(3)
    )
    sharp = _peak(T_true, tau=2e-4)

    def run(retry):
        rng = np.random.default_rng(4)
        prior = init_uniform_box(T_NOMINAL, 2e-3, np.deg2rad(5.0), 400, rng)
        pf = ParticleFilter(FIRM, "systematic", 0.5, rng, collapse_retry_iterations=retry)
        return pf.refine(prior, sharp, 1)

    plain, recovered = run(0), run(24)
    assert "ess_collapsed" in plain.flags and plain.diagnostics["min_ess"] < 2.0
    # without the retry: a confident wrong pose, the error 10x the reported spread
    t_plain, _ = _errors(plain.estimate, T_true)
    assert t_plain > 0.3 and t_plain > 10 * 1e3 * plain.spread.translation_rms_m
    assert "ess_collapsed" in recovered.flags  # still reported
    retry = recovered.diagnostics["collapse_retry"]
    assert retry["recovered"] and retry["iterations"] == 24 and retry["min_ess_before"] < 2.0
    assert recovered.diagnostics["min_ess"] > 100  # of 400
    assert _unique(recovered.particles.poses) > 200
    t_err, r_err = _errors(recovered.estimate, T_true)
    assert t_err < 0.1 and r_err < 0.3
    (record,) = step_warnings(3, recovered.diagnostics, 400)
    assert record["kind"] == "ess_collapsed" and record["recovered"] is True
    assert record["threshold"] == pytest.approx(4.0)  # 1% of 400
    assert "redone with 24 tempering iterations" in record["detail"] and "recovered" in record["detail"]


def test_collapsed_importance_update_is_recovered_by_the_tempered_sampler():
    rng = np.random.default_rng(5)
    T_true = perturb_about_origin(T_NOMINAL, np.array([1e-3, -5e-4, 0.0]), np.deg2rad([2.0, 0.0, -3.0]))
    prior = init_uniform_box(T_NOMINAL, 3e-3, np.deg2rad(10.0), 300, rng)
    pf = ParticleFilter(FIRM, "systematic", 0.5, rng, collapse_retry_iterations=16)
    result = pf.update(prior, _peak(T_true))
    assert "ess_collapsed" in result.flags and result.diagnostics["collapse_retry"]["recovered"]
    assert _unique(result.particles.poses) > 150
    assert _errors(result.estimate, T_true)[0] < 0.5


def test_collapse_threshold_has_a_floor_of_two_particles():
    pf = ParticleFilter(FIRM, "systematic", 0.5, np.random.default_rng(0))
    assert pf.collapse_threshold(500) == pytest.approx(5.0)
    assert pf.collapse_threshold(100) == pytest.approx(2.0)
    assert pf.collapse_threshold(3) == pytest.approx(1.5)


# -- 3. the estimate jumping further than the motion model allows -------------------------


def test_sudden_slip_is_reported_with_its_size_and_the_allowance():
    """Three frames on a still object, then it slips 2 mm in the gripper while the motion
    model allows 0.1 mm per frame: the jump is flagged with both numbers."""
    rng = np.random.default_rng(6)
    pf = ParticleFilter(FIRM, "systematic", 0.5, rng, refine_iterations=6)
    T_true = T_NOMINAL
    particles = init_from_prior(T_NOMINAL, 1e-3, np.deg2rad(2.0), 300, rng)
    for _ in range(3):
        previous = particles.spread()
        result = pf.step(particles, False, _peak(T_true, width_m=2e-3, tau=5e-4))
        particles = result.particles
        jump = check_jump(previous, result.estimate, *FIRM.sigmas(False), 5.0, 5e-5, np.deg2rad(0.05))
    assert not jump.jumped
    slipped = perturb_about_origin(T_true, np.array([2e-3, 0.0, 0.0]), np.zeros(3))
    previous = particles.spread()
    # the likelihood of a sharp, wide-reaching observation of the slipped pose
    result = pf.step(particles, True, _peak(slipped, width_m=4e-3, tau=5e-4))
    jump = check_jump(previous, result.estimate, *FIRM.sigmas(True), 5.0, 5e-5, np.deg2rad(0.05))
    assert jump.jumped and jump.ratio > 1.0
    assert jump.translation_m > jump.allowed_translation_m
    assert jump.allowed_translation_m < 1e-3  # 5 sigma of a sub-millimetre belief
    record = jump_warning(3, jump, 5.0)
    assert record["kind"] == "estimate_jump" and record["translation_mm"] == pytest.approx(1e3 * jump.translation_m)
    assert f"{1e3 * jump.translation_m:.2f} mm" in record["detail"]
    assert f"allows {1e3 * jump.allowed_translation_m:.2f} mm" in record["detail"]


# -- 4. a sensor that disagrees with all the others ---------------------------------------


def _frames(rng, n, bad=None, bad_from=0, bad_iou=0.15):
    """IoUs at the estimate for four sensors, frame by frame: clean sensors 0.9-1.0."""
    names = ("left", "right", "front", "side")
    for k in range(n):
        ious = {s: float(rng.uniform(0.9, 1.0)) for s in names}
        if bad is not None and k >= bad_from:
            ious[bad] = bad_iou
        yield k, ious, {s: True for s in names}


def test_a_sensor_disagreeing_for_five_frames_is_scaled_down():
    watch = SensorConsistency()
    events = []
    for k, ious, informative in _frames(np.random.default_rng(7), 12, bad="left", bad_from=2):
        events += [(k, *e) for e in watch.observe(ious, informative)]
    assert [(k, name) for k, name, *_ in events] == [(6, "left")]  # frames 2-6: five in a row
    assert events[0][2] == pytest.approx(0.15) and events[0][3] > 0.9
    assert watch.weight_factor("left") == pytest.approx(0.01)
    assert all(watch.weight_factor(s) == 1.0 for s in ("right", "front", "side"))


def test_clean_sensors_and_lone_disagreements_are_never_flagged():
    watch = SensorConsistency()
    rng = np.random.default_rng(8)
    for k, ious, informative in _frames(rng, 200):
        if k % 7 == 3:
            ious["front"] = 0.2  # one bad mask now and then
        assert watch.observe(ious, informative) == []
    assert watch.factors == {}


def test_one_frames_verdict_names_the_dissenter_and_skips_what_cannot_be_judged():
    watch = SensorConsistency()
    ious = {"left": 0.2, "right": 1.0, "front": 0.96, "side": 0.92}
    informative = {"left": True, "right": False, "front": True, "side": True}
    # right is out of contact (not informative); left has two informative others
    assert watch.disagreeing(ious, informative) == {"left": pytest.approx(0.94), "front": None, "side": None}
    # with one informative other left there is no majority to judge by
    assert watch.disagreeing(ious, {**informative, "side": False}) == {}
    # a sensor already scaled down is judged but no longer judges
    watch.factors["front"] = watch.factor
    assert watch.disagreeing(ious, informative) == {"front": None}
    assert watch.streak == {}  # a verdict alone counts nothing: observe() keeps the streaks


def test_no_majority_no_down_weighting():
    # two informative sensors that disagree: nobody to side with
    watch = SensorConsistency()
    for _ in range(20):
        assert watch.observe(
            {"front": 0.2, "side": 0.95, "left": 1.0}, {"front": True, "side": True, "left": False}
        ) == []
    # half the sensors disagreeing: at most half are ever scaled down
    watch = SensorConsistency()
    scaled = []
    for _ in range(20):
        scaled += watch.observe({"a": 0.1, "b": 0.1, "c": 0.95, "d": 0.97}, dict.fromkeys("abcd", True))
    assert len(watch.factors) <= 2


# -- reports ------------------------------------------------------------------------------


def test_warning_lines_give_one_line_per_kind_with_the_frame_count():
    records = [
        {"frame": k, "kind": "estimate_jump", "detail": f"jump {k}", "ratio": r}
        for k, r in ((3, 1.2), (4, 3.5), (9, 1.1))
    ] + [{"frame": None, "kind": "mesh_repaired", "detail": "cube.obj repaired"}]
    lines = warning_lines(records, 30)
    assert lines == ["estimate_jump in 3 of 30 frames (3, 4, 9): worst: jump 4", "mesh_repaired: cube.obj repaired"]
    assert count_warnings(records) == {"estimate_jump": 3, "mesh_repaired": 1}


def test_suspect_estimate_is_raised_when_enough_frames_leave_an_axis_open():
    # 4 of 10 frames with an open axis: at the 0.4 threshold the run is suspect, below it not
    pinned = [True] * 6 + [False] * 4
    w = suspect_warning(pinned, 0.4)
    assert w is not None and w["kind"] == "suspect_estimate" and w["frame"] is None
    assert w["unpinned_frames"] == 4 and w["frames"] == 10 and w["unpinned_fraction"] == pytest.approx(0.4)
    assert "4 of 10 frames (40 %" in w["detail"]
    assert suspect_warning(pinned, 0.41) is None
    assert suspect_warning([True] * 10, 0.1) is None
    # switched off, or no frame with evidence: never raised
    assert suspect_warning([False] * 10, None) is None
    assert suspect_warning([], 0.4) is None
    # the terminal line names it as a run warning
    assert warning_lines([w], 10) == [f"suspect_estimate: {w['detail']}"]


def test_a_rival_mode_is_a_frame_warning_and_makes_the_run_suspect():
    rival = RivalMode(frame=19, translation_mm=2.4, rotation_deg=3.3, nats_below=0.5)
    w = rival.warning()
    assert w["kind"] == "rival_mode" and w["frame"] == 19 and w["nats_below"] == 0.5
    assert "2.40 mm / 3.30 deg from the estimate explains the sensors within 0.5 nats of it" in w["detail"]
    assert "13.0 nats better than it" in RivalMode(9, 1.5, 0.2, -13.0).warning()["detail"]
    # a lead that rounds to nothing reads as a tie, not as "0.0 nats better"
    assert "explains the sensors within 0.0 nats of it" in RivalMode(29, 2.45, 0.35, -0.03).warning()["detail"]
    assert "0.1 nats better than it" in RivalMode(29, 2.45, 0.35, -0.06).warning()["detail"]
    # the run-level record: raised by the last check's rival even where every frame pinned the estimate
    run = suspect_warning([True] * 30, 0.4, rival)
    assert run["kind"] == "suspect_estimate" and run["frame"] is None and run["rival_frame"] == 19
    assert "at frame 19 another pose" in run["detail"] and "no later check ruled it out" in run["detail"]
    assert suspect_warning([True] * 30, 0.4, None) is None
    # the share of open frames decides first, whatever the rival
    assert "4 of 10 frames" in suspect_warning([True] * 6 + [False] * 4, 0.4, rival)["detail"]
