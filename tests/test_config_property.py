"""Property tests of the config loader: a wrong type, an out-of-range value or an unknown key,
at any nesting level, is rejected with one ConfigError line naming the file and the dotted key.

The fields are enumerated from the config dataclasses themselves, so a field added later is
covered without changing this file. ``masking.<sensor>.options`` is a free-form mapping
checked by the masking backend when an estimate starts (see docs/robustness.md), so no
unknown key is put inside it here.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal

import pytest
import yaml
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from mvtop_cli.config import Config, load_config
from mvtop_cli.errors import ConfigError

SETTINGS = settings(
    max_examples=150, derandomize=True, database=None, deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)

BASE: dict[str, Any] = {
    "object": {"name": "cube", "mesh": "cube.obj", "units": "m", "clearance_m": 0.0003,
               "symmetries": [{"xyz_m": [0.0, 0.0, 0.01], "rpy_deg": [180.0, 0.0, 0.0]}]},
    "environment": [{"name": "plate", "mesh": "cube.obj", "frame": "world",
                     "pose": {"xyz_m": [0.0, 0.0, -0.01], "rpy_deg": [0.0, 0.0, 0.0]}}],
    "sensors": {
        "cameras": [{"name": "front", "image_topic": "/front/image", "info_topic": "/front/camera_info",
                     "frame": "front_optical", "weight": 0.5}],
        "tactile": [{"name": "left", "image_topic": "/left/image", "info_topic": "/left/camera_info",
                     "depth_topic": "/left/depth", "gel_distance_m": 0.02}],
    },
    "topics": {"tf": "/tf", "wrench": "/wrench"},
    "frames": {"world": "world", "ee": "ee"},
    "robot": {},
    "grasp_prior": {"pose": {"xyz_m": [0.0, 0.0, 0.01]}, "distribution": "uniform", "translation_m": 0.002},
    "masking": {"camera": {"backend": "classical", "options": {}}, "tactile": {"backend": "difference"}},
    "filter": {"num_particles": 100, "temperature": 0.003, "seed": 3},
    "contact": {"margin_m": 0.0, "force_on_n": 2.0, "force_off_n": 1.0},
    "modalities": ["vision", "tactile", "contact"],
    "sync_tolerance_s": 0.02,
}


@dataclasses.dataclass(frozen=True)
class Leaf:
    """A config field: its dotted key, its path in the YAML data, its type and metadata."""

    key: str
    path: tuple
    type: Any
    meta: Any


def _item_type(tp: Any) -> Any | None:
    """X of ``tuple[X, ...]``, else None."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis:
        return args[0]
    return None


def _walk(
    cls: type, key: str, path: tuple, data: Any, leaves: list[Leaf], nodes: list[tuple[str, tuple, type]]
) -> None:
    """Collect the fields (leaves) and mapping nodes under dataclass ``cls`` at ``path``."""
    nodes.append((key, path, cls))
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("internal"):
            continue
        tp = hints[f.name]
        k = f"{key}.{f.name}" if key else f.name
        p = path + (f.name,)
        leaves.append(Leaf(k, p, tp, f.metadata))
        sub = data.get(f.name) if isinstance(data, dict) else None
        if dataclasses.is_dataclass(tp):
            _walk(tp, k, p, sub if isinstance(sub, dict) else {}, leaves, nodes)
        item = _item_type(tp)
        if item is not None and dataclasses.is_dataclass(item):
            for i, element in enumerate(sub or []):
                _walk(item, f"{k}[{i}]", p + (i,), element, leaves, nodes)


LEAVES: list[Leaf] = []
NODES: list[tuple[str, tuple, type]] = []
_walk(Config, "", (), BASE, LEAVES, NODES)
RANGED = [leaf for leaf in LEAVES if leaf.meta.get("lo") is not None or leaf.meta.get("hi") is not None]


def accepts(tp: Any, value: Any) -> bool:
    """Whether ``value`` has a type the loader should accept for ``tp`` (ranges aside).

    Written independently of the loader: the specification, not the implementation.
    """
    origin = typing.get_origin(tp)
    if tp is type(None):
        return value is None
    if origin in (typing.Union, types.UnionType):
        return any(accepts(a, value) for a in typing.get_args(tp))
    if origin is Literal:
        return isinstance(value, str) and value in typing.get_args(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(accepts(args[0], v) for v in value)
        return len(value) == len(args) and all(accepts(a, v) for a, v in zip(args, value))
    if origin is dict:
        return isinstance(value, dict)  # a mapping: its keys are another property's business
    if dataclasses.is_dataclass(tp):
        return value is None or isinstance(value, dict)  # a section left empty in YAML is null
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        try:
            return math.isfinite(float(value))
        except OverflowError:  # an integer beyond the float range
            return False
    if tp is str:  # names, topics, frames
        return isinstance(value, str) and value != "" and value.isprintable()
    if tp is Path:
        return isinstance(value, str) and value != "" and "\x00" not in value
    if tp is Any:
        return True
    raise AssertionError(f"unexpected config type {tp!r}")


def key_text(key: Any) -> str:
    """How a mapping key is quoted in a dotted key: as written if printable, else escaped."""
    text = str(key)
    return text if text and text.isprintable() and text.strip() == text else repr(text)


def with_value(path: tuple, value: Any) -> dict:
    data = copy.deepcopy(BASE)
    node = data
    for p in path[:-1]:
        node = node[p] if isinstance(p, int) else node.setdefault(p, {})
    node[path[-1]] = value
    return data


def same(a: Any, b: Any) -> bool:
    """Structural equality with NaN equal to NaN (YAML round trips)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("cfg")
    (d / "cube.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv 0 0 0.01\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    return d


def load(folder: Path, data: dict) -> tuple[Path, str | None]:
    """Write ``data`` as YAML and load it: (path, ConfigError message or None)."""
    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    assume(same(yaml.safe_load(text), data))  # the file holds exactly the intended data
    path = folder / "c.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        load_config(path)
    except ConfigError as err:
        return path, str(err)
    return path, None


def assert_names(message: str | None, path: Path, key: str) -> None:
    assert message is not None, f"{key}: accepted"
    assert "\n" not in message, message
    pattern = rf"{re.escape(str(path))}: {re.escape(key)}(\[\d+\])*: \S"
    assert re.match(pattern, message), f"expected the key {key!r} in: {message}"


def test_base_config_loads(folder):
    path = folder / "base.yaml"
    path.write_text(yaml.safe_dump(BASE, sort_keys=False))
    cfg = load_config(path)
    assert cfg.filter.num_particles == 100 and cfg.object.symmetries[0].rpy_deg == (180.0, 0.0, 0.0)
    # the walk reaches every level: list items, nested sections, poses in list items
    keys = {leaf.key for leaf in LEAVES}
    assert {"object.symmetries[0].xyz_m", "environment[0].pose.rpy_deg", "sensors.tactile[0].depth_topic",
            "masking.camera.backend", "filter.seed", "robot.urdf"} <= keys


VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**70), 2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["", "x", "1.5", "yes", "m", "systematic", "/a/b", "\x00", "~nosuchuser__/x"]),
    st.text(max_size=6),
    st.lists(st.one_of(st.integers(-5, 5), st.floats(-1, 1), st.text(max_size=2)), max_size=4),
    st.dictionaries(st.text(min_size=1, max_size=3), st.integers(), max_size=2),
)


@SETTINGS
@given(leaf=st.sampled_from(LEAVES), value=VALUES)
def test_wrong_types_name_the_dotted_key(folder, leaf, value):
    assume(not accepts(leaf.type, value))
    path, message = load(folder, with_value(leaf.path, value))
    assert_names(message, path, leaf.key)


ODD = st.sampled_from(["~nosuchuser__/mesh.obj", "x" * 5000, "a/" * 3000 + "m.obj", "\x00", "a\nb", "\u202e",
                       10**400, -(10**400), 2**63, 1e308, [[]], {"": None}])
LEAF_BY_KEY = {leaf.key: leaf for leaf in LEAVES}


@SETTINGS
@given(leaf=st.sampled_from(LEAVES), value=st.one_of(VALUES, ODD))
@example(leaf=LEAF_BY_KEY["object.mesh"], value="~nosuchuser__/mesh.obj")
@example(leaf=LEAF_BY_KEY["object.mesh"], value="x" * 5000)
@example(leaf=LEAF_BY_KEY["filter.temperature"], value=10**400)
@example(leaf=LEAF_BY_KEY["frames.ee"], value="a\nb")
def test_any_value_loads_or_fails_in_one_line(folder, leaf, value):
    """Whatever a field holds, loading ends in a config or in one ConfigError line naming the
    file and a dotted key, never in another exception."""
    path, message = load(folder, with_value(leaf.path, value))
    if message is not None:
        assert "\n" not in message, message
        assert re.match(rf"{re.escape(str(path))}: [^:\s]+: \S", message), message


def _outside(meta: dict, integer: bool, draw) -> Any:
    lo, hi = meta.get("lo"), meta.get("hi")
    options = []
    if lo is not None:
        below = draw(st.integers(1, 10**6)) if integer else draw(st.floats(1e-9, 1e6))
        options.append(lo - below)
        if meta.get("lo_open"):
            options.append(lo if integer else float(lo))
    if hi is not None:
        above = draw(st.integers(1, 10**6)) if integer else draw(st.floats(1e-9, 1e6))
        options.append(hi + above)
    if not integer:
        options += [math.nan, math.inf, -math.inf]
    return draw(st.sampled_from(options))


@SETTINGS
@given(leaf=st.sampled_from(RANGED), data=st.data())
def test_out_of_range_values_name_the_dotted_key(folder, leaf, data):
    tp = leaf.type
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    base_tp = args[0] if typing.get_origin(tp) in (typing.Union, types.UnionType) else tp
    if typing.get_origin(base_tp) is tuple:  # fixed-size list of numbers: one element out of range
        n = len(typing.get_args(base_tp))
        i = data.draw(st.integers(0, n - 1))
        value = [0.0] * n
        value[i] = _outside(leaf.meta, False, data.draw)
    else:
        value = _outside(leaf.meta, base_tp is int, data.draw)
    path, message = load(folder, with_value(leaf.path, value))
    assert_names(message, path, leaf.key)


KEYS = st.one_of(
    st.text(st.characters(blacklist_categories=("Cs",)), min_size=0, max_size=12),
    st.integers(-1000, 1000), st.booleans(), st.none(),
    st.sampled_from(["num_particle", "Mesh", "xyz", "camera ", "sensors.cameras", "a\nb", "\t"]),
)


@SETTINGS
@given(node=st.sampled_from(NODES), key=KEYS)
def test_unknown_keys_name_the_dotted_key(folder, node, key):
    prefix, path_in_data, cls = node
    names = {f.name for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    assume(not (isinstance(key, str) and key in names))
    data = copy.deepcopy(BASE)
    target = data
    for p in path_in_data:
        target = target[p] if isinstance(p, int) else target.setdefault(p, {})
    target[key] = 1
    path, message = load(folder, data)
    full = f"{prefix}.{key_text(key)}" if prefix else key_text(key)
    assert message is not None, f"unknown key {full!r} accepted"
    assert "\n" not in message, message
    assert message.startswith(f"{path}: {full}: unknown key"), message
