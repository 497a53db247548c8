"""``mvtop benchmark accuracy --scene``: one simulated camera scene per benchmark folder."""

from __future__ import annotations

import json

import pytest

from mvtop_cli.benchmarks.accuracy import AccuracyOptions, run_accuracy
from mvtop_cli.errors import MvtopError


@pytest.mark.parametrize("made_in, asked", [(None, "hard"), ("hard", "default")])
def test_a_folder_of_another_scene_is_refused_before_any_run(tmp_path, made_in, asked):
    run = tmp_path / "runs" / "cube_1000_M-VOP"
    run.mkdir(parents=True)
    bench = {"object": "cube", "seed": 1000, "method": "M-VOP", **({"scene": made_in} if made_in else {})}
    (run / "result.json").write_text(json.dumps({"benchmark": bench}))
    options = AccuracyOptions(objects=("cube",), poses=1, methods=("M-VOP",), scene=asked)
    with pytest.raises(MvtopError) as info:
        run_accuracy(tmp_path, options)
    assert str(info.value) == (f"{tmp_path}: holds runs of the {made_in or 'default'!r} scene, not {asked!r} "
                               "(expected one scene per benchmark folder: give another --out)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # nothing written
