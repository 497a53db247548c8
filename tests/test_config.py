"""Config loading: validation errors name the file and dotted key; defaults and paths resolve."""

import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from mvtop_cli.config import FilterConfig, PoseSpec, config_to_dict, dump_config, load_config, parse_config
from mvtop_cli.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]

BASE = """
object: {name: cube, mesh: cube.obj, clearance_m: 0.0003}
environment:
  - {name: receptacle, mesh: cube.obj, frame: world, pose: {xyz_m: [0, 0, 0.02]}}
sensors:
  cameras:
    - {name: front, image_topic: /cameras/front/image/compressed, info_topic: /cameras/front/camera_info}
  tactile:
    - {name: left, image_topic: /tactile/left/image, info_topic: /tactile/left/camera_info,
       depth_topic: /tactile/left/depth, frame: tactile_left_optical}
"""


@pytest.fixture
def cfg_dir(tmp_path: Path) -> Path:
    (tmp_path / "cube.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return tmp_path


def write(cfg_dir: Path, text: str, extra: dict | None = None) -> Path:
    data = yaml.safe_load(textwrap.dedent(text))
    for dotted, value in (extra or {}).items():
        node = data
        *parents, last = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    path = cfg_dir / "c.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_valid_config_resolves_paths_and_defaults(cfg_dir):
    cfg = load_config(write(cfg_dir, BASE))
    assert cfg.object.mesh == cfg_dir.resolve() / "cube.obj"
    assert cfg.filter == FilterConfig()  # every default filled in
    assert cfg.environment[0].pose.matrix()[2, 3] == pytest.approx(0.02)
    assert cfg.required_topics()["/cameras/front/image/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert cfg.required_topics()["/tactile/left/depth"] == "sensor_msgs/msg/Image"
    assert cfg.required_topics()["/contact"] == "std_msgs/msg/Bool"
    assert "tactile_left_optical" in cfg.required_frames()
    # the dump is complete and loads back to the same config
    dumped = yaml.safe_load(dump_config(cfg))
    assert dumped["filter"]["temperature"] == cfg.filter.temperature
    again = parse_config(dumped, cfg_dir / "again.yaml")
    assert again.object == cfg.object and again.filter == cfg.filter


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"filter.num_particle": 10}, "filter.num_particle: unknown key (did you mean 'num_particles'?)"),
        ({"filter.num_particles": 0}, "filter.num_particles: expected a value >= 1, got 0"),
        ({"filter.num_particles": 2.5}, "filter.num_particles: expected an integer, got 2.5"),
        ({"filter.temperature": 0}, "filter.temperature: expected a value > 0.0, got 0.0"),
        ({"filter.resampling": "sytematic"}, "did you mean 'systematic'?"),
        ({"contact.softness_m": "small"}, "contact.softness_m: expected a number, got 'small'"),
        ({"contact.penetration_softness_m": 0}, "contact.penetration_softness_m: expected a value > 0.0, got 0"),
        ({"object.units": "cm"}, "object.units: expected one of 'm', 'mm', got 'cm'"),
        ({"object.mesh": "missing.obj"}, "object.mesh: mesh file not found"),
        ({"modalities": ["vision", "tactle"]},
         "modalities[1]: expected one of 'vision', 'tactile', 'contact', got 'tactle' (did you mean 'tactile'?)"),
        ({"grasp_prior.pose": {"xyz_m": [0, 0]}}, "grasp_prior.pose.xyz_m: expected a list of 3 numbers, got 2 items"),
        ({"objcet": {}}, "objcet: unknown key (did you mean 'object'?)"),
    ],
)
def test_bad_values_name_file_and_key(cfg_dir, extra, message):
    path = write(cfg_dir, BASE, extra)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = str(info.value)
    assert text.startswith(f"{path}: ")
    assert message in text
    assert "\n" not in text


def test_missing_required_key(cfg_dir):
    path = write(cfg_dir, "sensors: {cameras: [{name: a, image_topic: /a, info_topic: /b}]}")
    with pytest.raises(ConfigError, match=r"c\.yaml: object: missing required key"):
        load_config(path)


def test_colour_bins_must_divide_the_channel_range(cfg_dir):
    path = write(cfg_dir, BASE, {"masking.camera_evidence": "colour", "masking.colour_bins": 24})
    with pytest.raises(ConfigError, match=r"masking\.colour_bins: expected a divisor of 256 \(e\.g\. 16\), got 24"):
        load_config(path)
    path = write(cfg_dir, BASE, {"masking.camera_evidence": "edges"})
    with pytest.raises(ConfigError, match=r"masking\.camera_evidence"):
        load_config(path)


def test_the_tactile_depth_tolerance_is_off_by_default_and_a_length_when_set(cfg_dir):
    assert load_config(write(cfg_dir, BASE)).masking.tactile_depth_tolerance_m is None
    cfg = load_config(write(cfg_dir, BASE, {"masking.tactile_depth_tolerance_m": 5e-5}))
    assert cfg.masking.tactile_depth_tolerance_m == 5e-5
    path = write(cfg_dir, BASE, {"masking.tactile_depth_tolerance_m": -1e-5})
    with pytest.raises(ConfigError, match=r"masking\.tactile_depth_tolerance_m: expected a value >= 0\.0, got -1e-05"):
        load_config(path)


def test_duplicate_sensor_names(cfg_dir):
    path = write(cfg_dir, BASE, {"sensors.tactile": [
        {"name": "front", "image_topic": "/t", "info_topic": "/ti"}]})
    with pytest.raises(ConfigError, match="sensor names must be unique, 'front' is used twice"):
        load_config(path)


def test_bad_yaml_and_missing_file(cfg_dir):
    bad = cfg_dir / "bad.yaml"
    bad.write_text("object: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: invalid YAML at line \d+"):
        load_config(bad)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(cfg_dir / "nope.yaml")


def test_pose_as_quaternion_equals_the_same_rotation_as_rpy(tmp_path):
    """grasp_prior.pose (any PoseSpec) takes quat_xyzw (ROS order) instead of rpy_deg; rpy_deg is
    extrinsic x-y-z, the matrix of tf2's setRPY: Rz(yaw) Ry(pitch) Rx(roll)."""
    rpy = (20.0, -35.0, 110.0)
    r, p, y = np.radians(rpy)
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    T_rpy = PoseSpec((0.01, 0.0, 0.02), rpy).matrix()
    np.testing.assert_allclose(T_rpy[:3, :3], Rz @ Ry @ Rx, atol=1e-12)
    q = Rotation.from_matrix(Rz @ Ry @ Rx).as_quat()  # x, y, z, w
    data = yaml.safe_load((REPO / "configs" / "cube.yaml").read_text())
    data["object"]["mesh"] = str(REPO / "configs" / "meshes" / "cube.obj")
    for e in data["environment"]:
        e["mesh"] = str(REPO / "configs" / e["mesh"])
    data["grasp_prior"]["pose"] = {"xyz_m": [0.01, 0.0, 0.02], "quat_xyzw": [float(v) for v in q]}
    cfg = parse_config(data, tmp_path / "q.yaml")
    np.testing.assert_allclose(cfg.grasp_prior.pose.matrix(), T_rpy, atol=1e-12)
    assert config_to_dict(cfg)["grasp_prior"]["pose"]["quat_xyzw"] == pytest.approx(list(q))
    assert "quat_xyzw" not in config_to_dict(cfg)["environment"][0]["pose"]  # unset: not written
    data["grasp_prior"]["pose"]["rpy_deg"] = [0, 0, 90]
    with pytest.raises(ConfigError, match=r"grasp_prior\.pose: give the rotation as rpy_deg or as quat_xyzw, not both"):
        parse_config(data, tmp_path / "q.yaml")
    data["grasp_prior"]["pose"] = {"quat_xyzw": [0, 0, 0, 2]}
    with pytest.raises(ConfigError, match=r"grasp_prior\.pose\.quat_xyzw\[3\]: expected a value <= 1.0"):
        parse_config(data, tmp_path / "q.yaml")
    data["grasp_prior"]["pose"] = {"quat_xyzw": [0, 0, 0.5, 0.5]}
    with pytest.raises(ConfigError, match=r"grasp_prior\.pose: quat_xyzw: expected a unit quaternion"):
        parse_config(data, tmp_path / "q.yaml")


# --- recorded masks (masking.camera.backend: topic) -------------------------------------------

TOPIC_MASKS = {"masking.camera.backend": "topic"}


def _with_mask_topic(cfg_dir: Path, extra: dict) -> Path:
    path = write(cfg_dir, BASE, extra)
    data = yaml.safe_load(path.read_text())
    data["sensors"]["cameras"][0]["mask_topic"] = "/cameras/front/mask"
    path.write_text(yaml.safe_dump(data))
    return path


def test_topic_backend_reads_each_cameras_mask_topic(cfg_dir):
    cfg = load_config(_with_mask_topic(cfg_dir, {**TOPIC_MASKS, "masking.camera.options": {"label": 3}}))
    assert cfg.sensors.cameras[0].mask_topic == "/cameras/front/mask"
    assert cfg.required_topics()["/cameras/front/mask"] == "sensor_msgs/msg/Image"
    assert cfg.masking.camera.options == {"label": 3}


def test_topic_backend_needs_a_mask_topic(cfg_dir):
    with pytest.raises(ConfigError, match=r"c\.yaml: sensors\.cameras\[0\]\.mask_topic: camera 'front' needs the "
                                          r"topic of its recorded object masks"):
        load_config(write(cfg_dir, BASE, TOPIC_MASKS))


def test_mask_topic_without_the_topic_backend_is_rejected(cfg_dir):
    with pytest.raises(ConfigError, match=r"sensors\.cameras\[0\]\.mask_topic: recorded masks are read only with "
                                          r"masking\.camera\.backend: topic \(the backend is 'classical'\)"):
        load_config(_with_mask_topic(cfg_dir, {}))


@pytest.mark.parametrize("options, key", [({"label": 0}, "label"), ({"label": "3"}, "label"),
                                          ({"label": True}, "label"), ({"labels": 3}, "labels")])
def test_topic_backend_options_are_checked_at_load(cfg_dir, options, key):
    with pytest.raises(ConfigError, match=rf"c\.yaml: masking\.camera\.options\.{key}: ") as info:
        load_config(_with_mask_topic(cfg_dir, {**TOPIC_MASKS, "masking.camera.options": options}))
    assert "\n" not in str(info.value)


def test_the_non_penetration_factor_is_on_by_default_and_null_turns_it_off(cfg_dir):
    assert load_config(write(cfg_dir, BASE)).contact.penetration_softness_m == 5e-5
    off = load_config(write(cfg_dir, BASE, {"contact.penetration_softness_m": None}))
    assert off.contact.penetration_softness_m is None and off.contact.penetration_tolerance_m == 1e-4


def test_settings_are_read_as_yaml_values_with_exponents_as_floats():
    from mvtop_cli.config import parse_settings

    got = parse_settings(["contact.softness_m=5e-5", "filter.num_particles=800", "masking.camera.backend=grabcut",
                          "sensors.cameras.0.name=left", "filter.sigma_low_m= 1.0e-4"])
    assert got == {"contact.softness_m": 5e-5, "filter.num_particles": 800, "masking.camera.backend": "grabcut",
                   "sensors.cameras.0.name": "left", "filter.sigma_low_m": 1e-4}
    assert isinstance(got["contact.softness_m"], float) and isinstance(got["filter.num_particles"], int)


@pytest.mark.parametrize("item, message", [
    ("contact.softness_m", "--set: expected KEY=VALUE with a dotted config key, e.g. contact.softness_m=1.0e-04, "
                           "got 'contact.softness_m'"),
    ("contact..softness_m=1", "--set: expected KEY=VALUE with a dotted config key, e.g. contact.softness_m=1.0e-04, "
                              "got 'contact..softness_m=1'"),
    ("=1", "--set: expected KEY=VALUE with a dotted config key, e.g. contact.softness_m=1.0e-04, got '=1'"),
    ("filter.temperature=[1", "--set filter.temperature: expected a YAML value, got '[1'"),
])
def test_a_malformed_setting_is_one_line_naming_it(item, message):
    from mvtop_cli.config import parse_settings

    with pytest.raises(ConfigError) as info:
        parse_settings([item])
    assert str(info.value) == message


def test_a_setting_given_twice_is_refused():
    from mvtop_cli.config import parse_settings

    with pytest.raises(ConfigError, match=r"^--set contact.softness_m: given twice$"):
        parse_settings(["contact.softness_m=1e-4", "contact.softness_m=2e-4"])


def test_settings_override_the_file_and_reach_the_typed_config(cfg_dir):
    path = cfg_dir / "config.yaml"
    path.write_text(BASE)
    cfg = load_config(path, {"contact.softness_m": 1e-4, "filter.num_particles": 800,
                             "sensors.cameras.0.name": "top"})
    assert cfg.contact.softness_m == 1e-4 and cfg.filter.num_particles == 800
    assert cfg.sensors.cameras[0].name == "top"
    assert load_config(path).contact.softness_m != 1e-4  # the file itself is unchanged
    assert yaml.safe_load(path.read_text()) == yaml.safe_load(BASE)


@pytest.mark.parametrize("settings, message", [
    ({"contact.softnes_m": 1e-4}, "contact.softnes_m: unknown key (did you mean 'softness_m'?)"),
    ({"contact.softness_m": -1.0}, "contact.softness_m: expected a value > 0.0, got -1.0"),
])
def test_a_setting_the_config_rejects_is_named_by_its_key(cfg_dir, settings, message):
    path = cfg_dir / "config.yaml"
    path.write_text(BASE)
    with pytest.raises(ConfigError) as info:
        load_config(path, settings)
    assert str(info.value) == f"{path}: {message}"


@pytest.mark.parametrize("key, message", [
    ("sensors.cameras.1.name", "--set sensors.cameras.1.name: sensors.cameras is a list of 1; expected an index 0-0, "
                               "got '1'"),
    ("object.name.first", "--set object.name.first: object.name is a value, not a section"),
])
def test_a_setting_through_a_value_or_past_a_list_is_refused(key, message):
    from mvtop_cli.config import apply_settings

    with pytest.raises(ConfigError) as info:
        apply_settings(yaml.safe_load(BASE), {key: "x"})
    assert str(info.value) == message
