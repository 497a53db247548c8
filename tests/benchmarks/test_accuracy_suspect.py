"""The benchmark's tally of the suspect_estimate warning: far-off runs (final insertion error
above 5 clearances) and runs within the clearance, flagged or not, per method; runs that did
not record their warnings are left out."""

from __future__ import annotations

from mvtop_cli.benchmarks.accuracy import format_table, suspect_tally


def _report(error_mm: float, suspect: bool | None, clearance_mm: float = 0.25, causes: list[str] | None = None) -> dict:
    bench = {} if suspect is None else {"warning_counts": {"suspect_estimate": 1} if suspect else {}}
    if causes is not None:
        bench["suspect"] = {"raised": bool(causes), "causes": causes}
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
    assert tally == {"M-VOP": {"runs": 5, "far_off": 2, "far_off_flagged": 1, "within": 2, "within_flagged": 1,
                               "far_off_recorded": 0, "far_off_causes": {}, "far_off_alone": {},
                               "within_recorded": 0, "within_causes": {}, "within_alone": {}}}
    text = format_table({"objects": ["conn1"], "table": {}, "suspect": tally})
    assert "- M-VOP: far off 1 flagged of 2; within the clearance 1 flagged of 2 (5 runs)" in text
    # without recorded warnings the section is left out (results made before they were kept)
    assert "suspect_estimate" not in format_table({"objects": ["conn1"], "table": {}, "suspect": {}})


def test_flagged_runs_that_recorded_why_are_counted_by_cause():
    """Runs that kept ``benchmark.suspect`` (summary.json ``suspect``) count per cause, and per
    cause that alone raised the warning; runs without it are counted as flagged only."""
    reports = {
        ("conn2", 1, "M-VOP"): _report(2.0, True, causes=["unpinned", "rival_mode"]),  # far off
        ("conn2", 2, "M-VOP"): _report(3.0, True, causes=["rival_mode"]),              # far off
        ("conn2", 3, "M-VOP"): _report(1.6, True),                                     # far off, why not kept
        ("conn2", 4, "M-VOP"): _report(0.1, True, causes=["unpinned"]),                # within: a false alarm
        ("conn2", 5, "M-VOP"): _report(0.2, False, causes=[]),                         # within, not flagged
    }
    t = suspect_tally(reports, ["M-VOP"])["M-VOP"]
    assert (t["far_off"], t["far_off_flagged"], t["far_off_recorded"]) == (3, 3, 2)
    assert t["far_off_causes"] == {"rival_mode": 2, "unpinned": 1} and t["far_off_alone"] == {"rival_mode": 1}
    assert (t["within"], t["within_flagged"], t["within_recorded"]) == (2, 1, 1)
    assert t["within_causes"] == {"unpinned": 1} and t["within_alone"] == {"unpinned": 1}
    text = format_table({"objects": ["conn2"], "table": {}, "suspect": {"M-VOP": t}})
    assert ("- M-VOP: far off 3 flagged of 3 (why: rival_mode 2 (alone 1), unpinned 1; 2 of 3 recorded); "
            "within the clearance 1 flagged of 2 (why: unpinned 1 (alone 1)) (5 runs)") in text
