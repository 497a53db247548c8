"""Tests for mvtop_cli.contact.grid: the contact grid is never silently coarser than the clearance."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.contact.grid import contact_grid

BOARD = np.array([[-0.1, -0.075, 0.0], [0.1, 0.075, 0.01]])


def test_small_receptacle_keeps_the_configured_resolution_without_warning():
    rec = np.array([[-0.02, -0.02, 0.01], [0.02, 0.02, 0.04]])
    bounds, res, warning = contact_grid([rec, BOARD], 0.05, 0.00025, 0.0003)
    assert res == 0.00025 and warning is None
    np.testing.assert_allclose(bounds, [[-0.025, -0.025, 0.005], [0.025, 0.025, 0.045]])


def test_wide_flange_grid_is_cut_to_the_reach_of_the_object_and_stays_fine():
    flange = np.array([[-0.05, -0.05, 0.01], [0.05, 0.05, 0.04]])  # a bore with a 10 cm flange
    bounds, res, warning = contact_grid([flange, BOARD], 0.05, 0.00025, 0.0003)
    assert res == 0.00025 and warning is None
    np.testing.assert_allclose(bounds[:, :2], [[-0.035, -0.035], [0.035, 0.035]])


def test_grid_coarser_than_the_clearance_warns_naming_both_numbers():
    flange = np.array([[-0.05, -0.05, 0.01], [0.05, 0.05, 0.04]])
    _, res, warning = contact_grid([flange, BOARD], 0.05, 0.00025, 0.0001, max_cells=1e6)
    assert res == pytest.approx(0.000626, abs=1e-6)
    assert "contact grid cells are 0.626 mm, coarser than the part's clearance of 0.1 mm" in warning
