"""Closed-loop insertion with test estimators: the truth inserts every grasp, an estimate off
by twice the clearance stalls on the rim, one off along the approach axis still reaches the
floor, a retry after re-estimation succeeds, same seed same run."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.geometry import se3
from mvtop_cli.sim.closed_loop import ControllerOptions, ground_truth_estimator, inserted_depth_m, run_insertion
from mvtop_cli.sim.episode import Collider, EpisodeOptions, apply_offset
from mvtop_cli.sim.object_file import resolve_object
from mvtop_cli.sim.objects import list_objects
from mvtop_cli.sim.scene import board_mesh, receptacle_pose

SEEDS = (0, 1, 2)


def _scene(name: str):
    spec = resolve_object(name)
    T_world_rec = receptacle_pose(spec.receptacle_mesh)
    return spec, T_world_rec, Collider(spec.mesh, [(spec.receptacle_mesh, T_world_rec), (board_mesh(), np.eye(4))])


def _insert(name: str, seed: int, estimate, controller: ControllerOptions = ControllerOptions()):
    spec, T_world_rec, collider = _scene(name)
    return run_insertion(T_world_rec, spec.insertion_depth_m, spec.grasp, spec.mesh, collider, EpisodeOptions(),
                         controller, np.random.default_rng(seed), estimate, squeeze=spec.grasp_squeeze)


@pytest.mark.parametrize("name", list_objects())
def test_perfect_estimator_inserts_every_grasp(name):
    spec, T_world_rec, collider = _scene(name)
    c = ControllerOptions()
    for seed in SEEDS:
        result = _insert(name, seed, ground_truth_estimator())
        assert result.success and len(result.attempts) == 1 and result.attempts[0].outcome == "inserted"
        assert result.attempts[0].align_error_m < 1e-9 and result.attempts[0].align_error_deg < 1e-4
        final = result.states[-1]
        depth = inserted_depth_m(T_world_rec, final.T_world_object)
        # down to the floor, 0.5 mm below the insertion depth (objects.FLOOR_GAP_MM), never through it
        assert spec.insertion_depth_m - c.compliance_m <= depth <= spec.insertion_depth_m + 0.0005 + 1e-6
        assert all(s.distance_m >= 0.0 for s in result.states)
        assert collider.distance(final.T_world_object) >= 0.0
        assert result.time_to_insert_s == pytest.approx(result.frames / 10.0)


@pytest.mark.parametrize("name", list_objects())
def test_estimate_off_by_twice_the_clearance_fails_the_first_attempt(name):
    spec, T_world_rec, _ = _scene(name)
    offset = se3.make_pose(np.eye(3), [2.0 * spec.clearance_m, 0.0, 0.0])  # along ee x: horizontal
    for seed in SEEDS:
        result = _insert(name, seed, ground_truth_estimator(offset))
        first = result.attempts[0]
        assert first.outcome == "stalled"
        assert first.depth_m < 0.001  # stopped on the rim, well above the insertion depth
        assert first.align_error_m == pytest.approx(2.0 * spec.clearance_m, rel=0.05)
        assert not result.success and len(result.attempts) == 3  # the same wrong estimate every retry
        assert [a.index for a in result.attempts] == [1, 2, 3]


@pytest.mark.parametrize("name", ["cube", "shaft_peg"])
def test_estimate_off_along_the_approach_axis_still_reaches_the_floor(name):
    """An estimate that puts the part 2 mm lower in the grasp than it is (along world z, the
    approach axis, which does not decide the alignment): the guarded descent goes on until the
    floor stops the part, and it inserts at the first attempt. A descent limited to 1 mm below
    the estimated depth ends in free air, 1 mm short of it, believed inserted."""
    spec, T_world_rec, _ = _scene(name)

    def lower(frame, truth):
        T_world_object = truth.T_world_object.copy()
        T_world_object[2, 3] -= 0.002
        return se3.invert(truth.T_world_ee) @ T_world_object

    for seed in SEEDS:
        result = _insert(name, seed, lower)
        assert [a.outcome for a in result.attempts] == ["inserted"] and result.success
        # stopped by the floor, 0.5 mm below the insertion depth (a tilted part's corner touches it first)
        assert spec.insertion_depth_m <= result.attempts[0].depth_m <= spec.insertion_depth_m + 0.0005 + 1e-6
        assert result.states[-1].contact
        short = _insert(name, seed, lower, ControllerOptions(overtravel_m=0.001))
        assert [a.outcome for a in short.attempts] == ["believed_inserted"] and not short.success
        assert short.attempts[0].depth_m == pytest.approx(spec.insertion_depth_m - 0.001, abs=2e-5)
        assert not short.states[-1].contact


def test_retry_with_a_corrected_estimate_inserts():
    """An estimate off by twice the clearance until the first contact and right from then on
    (as a filter that learns from contact): the first descent stalls, the second inserts."""
    spec, _, _ = _scene("cube")
    wrong = se3.make_pose(np.eye(3), [2.0 * spec.clearance_m, 0.0, 0.0])
    touched = []

    def estimate(frame, truth):
        if frame.contact:
            touched.append(frame.index)
        return truth.T_ee_object if touched else apply_offset(wrong, truth.T_ee_object)

    result = _insert("cube", 7, estimate)
    assert [a.outcome for a in result.attempts] == ["stalled", "inserted"] and result.success
    assert result.attempts[1].first_frame == result.attempts[0].last_frame + 1
    assert result.time_to_insert_s == pytest.approx(result.frames / 10.0)
    one = _insert("cube", 7, ground_truth_estimator(wrong), ControllerOptions(attempts=1))
    assert len(one.attempts) == 1 and not one.success


def test_same_seed_same_run():
    offset = se3.make_pose(se3.rotvec_to_matrix(np.radians([0.0, 1.5, 0.0])), [0.0002, 0.0, 0.0])
    a = _insert("plug", 11, ground_truth_estimator(offset))
    b = _insert("plug", 11, ground_truth_estimator(offset))
    c = _insert("plug", 12, ground_truth_estimator(offset))
    assert a.attempts == b.attempts and a.frames == b.frames
    for sa, sb in zip(a.states, b.states):
        assert np.array_equal(sa.T_world_ee, sb.T_world_ee) and np.array_equal(sa.T_ee_object, sb.T_ee_object)
    assert not np.array_equal(a.states[0].T_world_ee, c.states[0].T_world_ee)


def test_controller_options_are_checked():
    with pytest.raises(ValueError, match="attempts"):
        ControllerOptions(attempts=0)
    with pytest.raises(ValueError, match="descent_step_m"):
        ControllerOptions(descent_step_m=0.0)
