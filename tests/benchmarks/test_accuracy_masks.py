"""``mvtop benchmark accuracy --recorded-masks-px``: a simulated segmenter's camera masks recorded
with the images and read by the estimator (``topic`` backend). One kind of camera masks per
folder: ``test_folder_checks.py``."""

from __future__ import annotations

import json

import numpy as np
import yaml

from mvtop_cli.benchmarks.accuracy import AccuracyOptions, format_table, run_accuracy


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
