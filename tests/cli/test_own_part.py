"""Your own part, through the command line alone: the IndustReal 12 mm peg and its tray insert (real
CAD, metres, a tray that is watertight only after merging its split vertices) go from the raw
files to an object file (mesh-check), a simulated log with its config (simulate --object-file
--write-config), an estimate and an evaluation."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from _real_data import REAL_DATA, needs_real_data

REPO = Path(__file__).resolve().parents[2]
MESHES = REAL_DATA / "industreal_meshes"


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", "mvtop_cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr
    return proc


@needs_real_data
def test_industreal_peg_from_raw_cad_to_an_evaluated_estimate(tmp_path):
    peg = MESHES / "industreal_rectangular_peg_12mm.obj"
    tray = MESHES / "industreal_tray_insert_rectangular_peg_12mm.obj"
    out = run("mesh-check", str(peg), "--receptacle", str(tray), "--name", "peg12", "--out", "peg12.yaml",
              cwd=tmp_path).stdout
    assert "object mesh: units: m: the part is 0.05 file units across" in out
    assert "receptacle mesh: receptacle mesh is not watertight" in out and "merged 4160 coincident vertices" in out
    assert "symmetries: 4 proper symmetries" in out
    assert "clearance (free travel at the inserted pose) [mm]: -x 0.521, +x 0.521, -y 0.545, +y 0.545" in out
    part = yaml.safe_load((tmp_path / "peg12.yaml").read_text())
    assert part["insertion_depth_m"] == pytest.approx(0.0245, abs=1e-6)
    assert part["clearance_m"] == pytest.approx(0.000521, abs=2e-6)
    assert len(part["symmetries"]["discrete"]) == 3

    run("simulate", "--object-file", "peg12.yaml", "--seed", "3", "--frames", "6", "--resolution", "320x240",
        "--out", "peg12.mcap", "--write-config", "peg12_config.yaml", cwd=tmp_path)
    cfg = yaml.safe_load((tmp_path / "peg12_config.yaml").read_text())
    assert cfg["object"]["name"] == "peg12" and len(cfg["object"]["symmetries"]) == 3
    assert (tmp_path / "meshes" / "peg12_receptacle.obj").is_file()

    run("estimate", "peg12.mcap", "--config", "peg12_config.yaml", "--out", "est", "--particles", "40", cwd=tmp_path)
    run("eval", "est", "--log", "peg12.mcap", "--out", "eval", cwd=tmp_path)
    report = json.loads((tmp_path / "eval" / "report.json").read_text())
    assert report["object"] == "peg12" and report["symmetries"] == 3
    assert report["clearance_mm"] == pytest.approx(0.521, abs=0.002)
    assert report["final"]["pose_error_mm"] < 3.0  # the prior alone spreads 3 mm and 10 deg
