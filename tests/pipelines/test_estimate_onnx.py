"""The ONNX masking backends run inside `mvtop estimate` and `render-masks`, chosen by config,
with tiny test models of the real signatures (no weights are downloaded)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate
from mvtop_cli.pipelines.render_masks import RenderMasksOptions, render_masks

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("onnx_models", ROOT / "tests" / "masking" / "onnx_models.py")
onnx_models = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(onnx_models)


def _config(tmp: Path, name: str, camera: dict) -> Path:
    data = yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())
    meshes = ROOT / "configs"
    data["object"]["mesh"] = str(meshes / data["object"]["mesh"])
    for e in data["environment"]:
        e["mesh"] = str(meshes / e["mesh"])
    data["masking"] = {"camera": camera}
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def sam_models(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("sam")
    return {
        "encoder_path": str(onnx_models.sam_encoder(tmp / "encoder.onnx")),
        "decoder_path": str(onnx_models.sam_decoder(tmp / "decoder.onnx", miss_radius=6.0)),
        "points_per_side": 4, "pred_iou_thresh": 0.1, "stability_score_thresh": 0.0,
        "min_mask_area_px": 10, "min_region_area_px": 10,
    }


def test_sam_backend_runs_inside_estimate(tmp_path, sam_models, monkeypatch):
    from mvtop_cli.masking import onnx_sam

    calls = {"proposals": 0}
    original = onnx_sam.SamOnnxBackend.proposals

    def counting(self, image, context=None):
        calls["proposals"] += 1
        return original(self, image, context)

    monkeypatch.setattr(onnx_sam.SamOnnxBackend, "proposals", counting)
    cfg = load_config(_config(tmp_path, "conn2", {"backend": "sam_onnx", "options": sam_models}))
    summary = estimate(ROOT / "sample_logs" / "conn2.mcap", cfg, tmp_path / "out",
                       EstimateOptions(modalities=("vision",), num_particles=60, max_frames=2))
    assert summary["frames_processed"] == 2
    assert summary["masking"]["camera"] == "sam_onnx"
    assert calls["proposals"] >= 2  # both cameras of the first frame asked the model
    resolved = yaml.safe_load((tmp_path / "out" / "config.resolved.yaml").read_text())
    assert resolved["masking"]["camera"]["backend"] == "sam_onnx"


def test_sam_prompt_masks_show_in_render_masks(tmp_path, sam_models):
    # the test decoder answers a prompt that hits nothing it knows with a 6 px disc
    cfg = load_config(_config(tmp_path, "conn2", {"backend": "sam_onnx", "options": sam_models}))
    out = tmp_path / "masks"
    render_masks(ROOT / "sample_logs" / "conn2.mcap", cfg, out, None, RenderMasksOptions(frames=(3,), video=False))
    observed = cv2.imread(str(out / "frame_0003_front_observed.png"), cv2.IMREAD_GRAYSCALE) > 127
    assert abs(observed.sum() - np.pi * 6**2) < 0.25 * np.pi * 6**2


def test_instance_backend_runs_inside_estimate(tmp_path):
    model = onnx_models.instance_model(tmp_path / "maskrcnn.onnx")
    camera = {"backend": "instance_onnx", "options": {"model_path": str(model), "class_id": 1, "score_threshold": 0.5}}
    cfg = load_config(_config(tmp_path, "plug", camera))
    summary = estimate(ROOT / "sample_logs" / "plug.mcap", cfg, tmp_path / "out",
                       EstimateOptions(modalities=("vision", "tactile"), num_particles=60, max_frames=2))
    assert summary["masking"]["camera"] == "instance_onnx" and summary["frames_processed"] == 2


def test_missing_model_is_a_one_line_error(tmp_path):
    from mvtop_cli.errors import MvtopError

    camera = {"backend": "sam_onnx", "options": {"encoder_path": "nope/enc.onnx", "decoder_path": "nope/dec.onnx"}}
    cfg = load_config(_config(tmp_path, "conn2", camera))
    with pytest.raises(MvtopError) as info:
        estimate(ROOT / "sample_logs" / "conn2.mcap", cfg, tmp_path / "out", EstimateOptions(max_frames=1))
    assert "enc.onnx" in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()
