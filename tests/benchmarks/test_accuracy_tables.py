"""``benchmark accuracy``'s tables: the final NEES calibration per object and method beside the
success rates, left out for runs that reported no covariance."""

from __future__ import annotations

from mvtop_cli.benchmarks.accuracy import format_table


def _cell(success: float, nees: float | None) -> dict:
    err = {"median": 0.1, "p95": 0.2}
    return {"pose_error_mm": err, "rotation_error_deg": err, "success_rate": success,
            "nees_within_bound_fraction": nees}


def test_the_nees_table_gives_each_objects_share_within_the_bound_and_their_average():
    summary = {"objects": ["cube", "conn1"],
               "table": {"M-VOP": {"cube": _cell(0.7, 0.95), "conn1": _cell(0.1, 1.0)},
                         "M-TOP": {"cube": _cell(0.2, 0.78)}}}
    lines = format_table(summary).split("## Final NEES within its chi-square 95 % bound")[1].splitlines()
    assert "| M-VOP | 95 | 100 | 98 |" in lines  # avg over the objects: 97.5 rounds to even
    assert "| M-TOP | 78 | - | 78 |" in lines
    none = {"objects": ["cube"], "table": {"M-VOP": {"cube": _cell(0.7, None)}}}
    assert "NEES" not in format_table(none)
