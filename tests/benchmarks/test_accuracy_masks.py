"""``mvtop benchmark accuracy --recorded-masks-px``: a simulated segmenter's camera masks recorded
with the images and read by the estimator (``topic`` backend); one kind of camera masks per
benchmark folder (``benchmarks.runs.check_masks``, shared with ``benchmark insertion``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from mvtop_cli.benchmarks.accuracy import AccuracyOptions, format_table, run_accuracy
from mvtop_cli.errors import MvtopError


@pytest.mark.parametrize("made_with, asked, message", [
    (None, 0, "camera masks made from the images, not --recorded-masks-px 0"),
    (1, None, "--recorded-masks-px 1, not camera masks made from the images"),
])
def test_a_folder_of_other_camera_masks_is_refused_before_any_run(tmp_path, made_with, asked, message):
    run = tmp_path / "runs" / "cube_1000_M-VOP"
    run.mkdir(parents=True)
    bench = {"object": "cube", "seed": 1000, "method": "M-VOP",
             **({} if made_with is None else {"recorded_masks_px": made_with})}
    (run / "result.json").write_text(json.dumps({"benchmark": bench}))
    options = AccuracyOptions(objects=("cube",), poses=1, methods=("M-VOP",), recorded_masks_px=asked)
    with pytest.raises(MvtopError) as info:
        run_accuracy(tmp_path, options)
    assert str(info.value) == (f"{tmp_path}: its runs were made with {message} (one setting per benchmark folder: "
                               "give another --out)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # nothing written


def test_recorded_masks_reach_the_estimator_and_the_record(tmp_path):
    """With exact recorded masks the scene's log carries each camera's mask, its config reads them
    (``topic``), the run records the setting and the tables name it; the simulated grasp is the
    one the image masks' folder simulates for the same seed."""
    from mvtop_cli.io.mcap_reader import McapLog

    small = dict(objects=("cube",), poses=1, methods=("M-VOP",), frames=4, particles=40)
    summary = run_accuracy(tmp_path / "rec", AccuracyOptions(**small, recorded_masks_px=0))
    scene = tmp_path / "rec" / "scenes" / "cube_1000"
    cfg = yaml.safe_load((scene / "config.yaml").read_text())
    assert cfg["masking"]["camera"]["backend"] == "topic"
    assert [c["mask_topic"] for c in cfg["sensors"]["cameras"]] == ["/cameras/front/mask", "/cameras/side/mask"]
    with McapLog(scene / "log.mcap") as log:
        assert {"/cameras/front/mask", "/cameras/side/mask"} <= set(log.summary().topic_names)
    run = tmp_path / "rec" / "runs" / "cube_1000_M-VOP"
    assert json.loads((run / "summary.json").read_text())["masking"]["camera"] == "topic"
    report = json.loads((run / "result.json").read_text())
    assert report["benchmark"]["recorded_masks_px"] == 0 and summary["recorded_masks_px"] == 0
    assert ", camera masks recorded by a simulated segmenter (exact))" in format_table(summary).splitlines()[0]

    plain = run_accuracy(tmp_path / "img", AccuracyOptions(**small))
    assert plain["recorded_masks_px"] is None and "segmenter" not in format_table(plain)
    other = json.loads((tmp_path / "img" / "runs" / "cube_1000_M-VOP" / "result.json").read_text())
    assert "recorded_masks_px" not in other["benchmark"]
    truth = [np.array(r["final"]["T_world_object_truth"]["translation_m"]) for r in (report, other)]
    assert np.array_equal(truth[0], truth[1])
