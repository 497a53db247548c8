"""Tests for mvtop_cli.sim.object_file: the object file format, its validation, frames, and the
built-in objects as object files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mvtop_cli.errors import ConfigError
from mvtop_cli.io.meshes import write_obj
from mvtop_cli.sim.object_file import load_object_file, object_file_dict, read_object_file
from mvtop_cli.sim.objects import builtin_object_file, get_object, list_objects

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", list_objects())
def test_builtin_object_file_is_current_and_loads_to_the_builtin_object(name):
    path = REPO / "configs" / "objects" / f"{name}.yaml"
    assert yaml.safe_load(path.read_text()) == object_file_dict(builtin_object_file(name)), (
        f"{path} is stale: run scripts/make_samples.py")
    loaded, spec = load_object_file(path), get_object(name)
    assert loaded.name == name
    np.testing.assert_allclose(loaded.mesh.vertices, spec.mesh.vertices, atol=1e-12)
    np.testing.assert_array_equal(loaded.mesh.faces, spec.mesh.faces)
    np.testing.assert_allclose(loaded.receptacle_mesh.vertices, spec.receptacle_mesh.vertices, atol=1e-12)
    np.testing.assert_array_equal(loaded.grasp, spec.grasp)
    np.testing.assert_allclose(loaded.symmetry, spec.symmetry, atol=1e-15)
    for key in ("insertion_depth_m", "clearance_m", "grasp_width_m", "metallic", "roughness"):
        assert getattr(loaded, key) == pytest.approx(getattr(spec, key), abs=1e-15)
    assert (loaded.color_rgba, loaded.material) == (spec.color_rgba, spec.material)
    assert loaded.grasp_squeeze == spec.grasp_squeeze == "widest"  # as the sample logs were made


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "part.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _peg_files(tmp_path: Path) -> dict:
    """The built-in shaft peg as a user's CAD: millimetres, upside down (the leading face at +z),
    and the tray in millimetres with its mouth at z = 0 of a box ranging below."""
    spec = get_object("shaft_peg")
    peg = spec.mesh.copy()
    peg.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))  # turned 180 deg about x
    peg.apply_translation([0.0, 0.0, 0.050])
    peg.apply_scale(1000.0)
    tray = spec.receptacle_mesh.copy()
    tray.apply_scale(1000.0)
    write_obj(peg, tmp_path / "peg.obj")
    write_obj(tray, tmp_path / "tray.obj")
    return {"name": "peg", "object": {"mesh": "peg.obj", "units": "mm", "frame": "+z"},
            "receptacle": {"mesh": "tray.obj", "units": "mm", "frame": "+z"},
            "insertion_depth_m": 0.0245, "clearance_m": 0.0003}


def test_frame_from_the_leading_face_and_units_give_the_builtin_geometry(tmp_path):
    spec = load_object_file(_write(tmp_path, _peg_files(tmp_path)))
    ref = get_object("shaft_peg")
    np.testing.assert_allclose(spec.mesh.bounds, ref.mesh.bounds, atol=1e-9)
    np.testing.assert_allclose(spec.receptacle_mesh.bounds, ref.receptacle_mesh.bounds, atol=1e-9)
    # the default grasp is the lowest whose fingertips clear the receptacle: the built-in's 33 mm
    assert spec.grasp[2, 3] == pytest.approx(0.03295, abs=1e-9)
    assert spec.grasp_width_m == pytest.approx(0.00791, abs=1e-9)


def test_pad_width_is_taken_where_the_pads_are(tmp_path):
    data = _peg_files(tmp_path)
    plug = get_object("plug")  # blades 1.52 x 6.35 mm below a 30 x 22 mm body
    write_obj(plug.mesh, tmp_path / "plug.obj")
    data["object"] = {"mesh": "plug.obj"}
    data["grasp"] = {"height_m": 0.006}  # the pads on the blades only
    data["insertion_depth_m"] = 0.0
    spec = load_object_file(_write(tmp_path, data))
    assert spec.grasp_width_m == pytest.approx(0.00635, abs=1e-9)  # not the 22 mm of the body


@pytest.mark.parametrize(("patch", "message"), [
    ({"clearence_m": 0.001}, "part.yaml: clearence_m: unknown key (did you mean 'clearance_m'?)"),
    ({"object": {"mesh": "peg.obj", "frame": "+w"}}, "part.yaml: object.frame: expected one of"),
    ({"clearance_m": 0.5}, "part.yaml: clearance_m: expected a value <= 0.01, got 0.5"),
    ({"symmetries": {"continuous": {"axis": [0, 0, 0]}}}, "part.yaml: symmetries.continuous.axis: expected a "
                                                          "non-zero direction"),
    ({"directional_clearance": {"x_m": [0.0001, 0.0002], "y_m": [0.0007, 0.0007]}},
     "part.yaml: clearance_m: expected the smallest value of directional_clearance, 0.0001, got 0.0003"),
    ({"grasp": {"height_m": 0.2}}, "part.yaml: grasp.height_m: expected a height on the part"),
])
def test_bad_object_files_fail_with_one_line_naming_file_and_key(tmp_path, patch, message):
    data = {**_peg_files(tmp_path), **patch}
    with pytest.raises(ConfigError) as err:
        load_object_file(_write(tmp_path, data))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_missing_object_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="object file not found"):
        read_object_file(tmp_path / "nope.yaml")
