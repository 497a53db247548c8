"""Tests for mvtop_cli.sim.mesh_check: units, repairs, simplification, symmetries, clearance."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.eval.metrics import symmetry_group
from mvtop_cli.sim.mesh_check import find_symmetries, guess_units, measure_fit, simplification_error, simplify
from mvtop_cli.sim.objects import get_object


@pytest.mark.parametrize(("name", "count"), [("cube", 24), ("shaft_peg", 4), ("plug", 2), ("conn1", 1), ("conn2", 1)])
def test_symmetries_found_numerically_match_the_builtin_parts(name, count):
    spec = get_object(name)
    discrete, continuous = find_symmetries(spec.mesh, 2e-5)
    assert continuous is None
    found = symmetry_group(np.stack(discrete) if discrete else None)
    assert len(found) == count == len(spec.symmetry)
    # the same transforms as the hand-written ones
    for S in spec.symmetry:
        assert min(np.abs(S - F).max() for F in found) < 1e-9


def test_a_cylinder_has_a_continuous_symmetry_and_an_end_for_end_turn():
    cyl = trimesh.creation.cylinder(radius=0.004, height=0.05, sections=256)
    cyl.apply_translation([0.0, 0.0, 0.025])
    discrete, continuous = find_symmetries(cyl, 2e-5)
    assert continuous is not None and continuous.axis == (0.0, 0.0, 1.0)
    np.testing.assert_allclose(continuous.point_m, [0.0, 0.0, 0.025], atol=1e-9)
    assert len(discrete) == 1 and discrete[0][2, 2] == pytest.approx(-1.0)


def test_units_are_read_off_the_size():
    assert guess_units(50.0)[0] == "mm" and "50 m if read as metres" in guess_units(50.0)[1]
    assert guess_units(0.05)[0] == "m"


def test_simplified_copy_has_fewer_faces_and_its_error_is_measured():
    cyl = trimesh.creation.cylinder(radius=0.004, height=0.05, sections=2000)
    small = simplify(cyl, 1000)
    assert len(small.faces) <= 1000
    err = simplification_error(cyl, small)
    assert 0.0 < err < 2e-4


def test_clearance_and_depth_measured_from_the_builtin_pair():
    spec = get_object("shaft_peg")  # 0.3 mm per side, hole floor 0.5 mm below the inserted face
    findings: list[str] = []
    fit = measure_fit(spec.mesh, spec.receptacle_mesh, findings)
    assert fit["depth"] == pytest.approx(spec.insertion_depth_m, abs=1e-6)
    np.testing.assert_allclose(fit["travel"], [3e-4] * 4, atol=2e-6)
    np.testing.assert_allclose(fit["offset"], [0.0, 0.0], atol=1e-6)
    assert any(f.startswith("clearance (free travel") for f in findings)


def test_an_off_centre_bore_is_found_and_reported():
    spec = get_object("shaft_peg")
    rec = spec.receptacle_mesh.copy()
    rec.apply_translation([0.0002, 0.0, 0.0])  # within the clearance: it still goes in
    findings: list[str] = []
    fit = measure_fit(spec.mesh, rec, findings)
    np.testing.assert_allclose(fit["offset"], [0.0002, 0.0], atol=2e-6)
    np.testing.assert_allclose(fit["travel"], [3e-4] * 4, atol=2e-6)
    assert any("bore's centre is at (0.2, 0) mm" in f for f in findings)
