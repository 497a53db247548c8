"""One simulated camera scene, one kind of camera masks and one set of config settings per
benchmark folder, for ``benchmark accuracy`` and ``benchmark insertion`` alike (the checks are
``benchmarks.runs.check_scene``, ``check_masks`` and ``check_settings``, shared by both): a folder
made otherwise is refused before any run, naming both."""

from __future__ import annotations

import json

import pytest

from mvtop_cli.benchmarks.accuracy import AccuracyOptions, run_accuracy
from mvtop_cli.benchmarks.insertion import InsertionBenchmarkOptions, run_insertion_benchmark
from mvtop_cli.errors import MvtopError

BENCHMARKS = {
    "accuracy": (run_accuracy, AccuracyOptions, {}),
    "insertion": (run_insertion_benchmark, InsertionBenchmarkOptions, {"attempts_allowed": 3}),
}


def _refused(kind: str, folder, made_with: dict, **asked) -> str:
    """The error of benchmark ``kind`` asked with ``asked`` options in ``folder``, which holds
    one finished cube M-TOP run whose ``benchmark`` record adds ``made_with``; checks that
    nothing was written."""
    run_fn, options_cls, record = BENCHMARKS[kind]
    run = folder / "runs" / "cube_1000_M-TOP"
    run.mkdir(parents=True)
    bench = {"object": "cube", "seed": 1000, "method": "M-TOP", **record, **made_with}
    (run / "result.json").write_text(json.dumps({"benchmark": bench}))
    with pytest.raises(MvtopError) as info:
        run_fn(folder, options_cls(objects=("cube",), poses=1, methods=("M-TOP",), **asked))
    assert sorted(p.name for p in folder.iterdir()) == ["runs"]  # nothing written
    return str(info.value)


@pytest.mark.parametrize("kind", sorted(BENCHMARKS))
@pytest.mark.parametrize("made_in, asked", [(None, "hard"), ("hard", "default")])
def test_a_folder_of_another_scene_is_refused_before_any_run(tmp_path, kind, made_in, asked):
    message = _refused(kind, tmp_path, {"scene": made_in} if made_in else {}, scene=asked)
    assert message == (f"{tmp_path}: holds runs of the {made_in or 'default'!r} scene, not {asked!r} "
                       "(expected one scene per benchmark folder: give another --out)")


@pytest.mark.parametrize("kind", sorted(BENCHMARKS))
@pytest.mark.parametrize("made_with, asked, message", [
    (None, 1, "camera masks made from the images, not --recorded-masks-px 1"),
    (0, None, "--recorded-masks-px 0, not camera masks made from the images"),
    (0, 2, "--recorded-masks-px 0, not --recorded-masks-px 2"),
])
def test_a_folder_of_other_camera_masks_is_refused_before_any_run(tmp_path, kind, made_with, asked, message):
    made = {} if made_with is None else {"recorded_masks_px": made_with}
    assert _refused(kind, tmp_path, made, recorded_masks_px=asked) == (
        f"{tmp_path}: its runs were made with {message} (one setting per benchmark folder: give another --out)")


@pytest.mark.parametrize("kind", sorted(BENCHMARKS))
@pytest.mark.parametrize("made_with, asked, message", [
    (None, {"contact.softness_m": 5e-5}, "no --set, not --set contact.softness_m=5e-05"),
    ({"contact.softness_m": 5e-5}, {}, "--set contact.softness_m=5e-05, not no --set"),
    ({"contact.softness_m": 5e-5}, {"contact.softness_m": 1e-4}, "--set contact.softness_m=5e-05, not --set "
                                                                 "contact.softness_m=0.0001"),
])
def test_a_folder_of_other_settings_is_refused_before_any_run(tmp_path, kind, made_with, asked, message):
    made = {} if made_with is None else {"settings": made_with}
    assert _refused(kind, tmp_path, made, settings=asked) == (
        f"{tmp_path}: its runs were made with {message} (one setting per benchmark folder: give another --out)")
