"""The benchmark's tally of the suspect_estimate warning: far-off runs (final insertion error
above 5 clearances) and runs within the clearance, flagged or not, per method; runs that did
not record their warnings are left out."""

from __future__ import annotations

from mvtop_cli.benchmarks.accuracy import format_table, suspect_tally


def _report(error_mm: float, suspect: bool | None, clearance_mm: float = 0.25) -> dict:
    bench = {} if suspect is None else {"warning_counts": {"suspect_estimate": 1} if suspect else {}}
    return {"clearance_mm": clearance_mm, "benchmark": bench,
            "final": {"insertion_error_mm": error_mm, "insertable": error_mm <= clearance_mm,
                      "translation_error_mm": error_mm}}


def test_far_off_and_within_runs_are_counted_with_their_flags():
    reports = {
        ("conn1", 1, "M-VOP"): _report(2.0, True),     # far off (8 clearances), flagged
        ("conn1", 2, "M-VOP"): _report(1.3, False),    # far off (5.2), missed
        ("conn1", 3, "M-VOP"): _report(1.25, True),    # exactly 5 clearances: not far off, not within
        ("conn1", 4, "M-VOP"): _report(0.1, True),     # within, a false alarm
        ("conn1", 5, "M-VOP"): _report(0.25, False),   # within (at the clearance)
        ("conn1", 6, "M-VOP"): _report(3.0, None),     # warnings not recorded: left out
        ("conn1", 1, "M-VTOP"): _report(0.1, None),    # a method without recorded warnings
    }
    tally = suspect_tally(reports, ["M-VTOP", "M-VOP"])
    assert tally == {"M-VOP": {"runs": 5, "far_off": 2, "far_off_flagged": 1, "within": 2, "within_flagged": 1}}
    text = format_table({"objects": ["conn1"], "table": {}, "suspect": tally})
    assert "- M-VOP: far off 1 flagged of 2; within the clearance 1 flagged of 2 (5 runs)" in text
    # without recorded warnings the section is left out (results made before they were kept)
    assert "suspect_estimate" not in format_table({"objects": ["conn1"], "table": {}, "suspect": {}})
