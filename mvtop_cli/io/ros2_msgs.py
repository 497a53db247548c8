"""ROS 2 message definitions (``ros2msg`` schema texts) for every type mvtop reads or writes.

rosbag2 stores a type's schema as its own ``.msg`` text followed by the text of every
type it depends on, each once, depth first in field order, each introduced by a line of
80 ``=`` and a ``MSG: pkg/Name`` line. ``mcap_ros2`` parses exactly that layout, so
``definition(type_name)`` builds it from the field lists below.

The field lists follow the ROS 2 interface definitions (common_interfaces,
rcl_interfaces); the comments are ours.
"""

from __future__ import annotations

import re

# One entry per message type: its own fields only (dependencies are appended by
# ``definition``). Names are the full ``pkg/msg/Name`` form rosbag2 uses for schemas.
_OWN_TEXT: dict[str, str] = {
    "builtin_interfaces/msg/Time": """\
# Time since the epoch: sec [s] plus nanosec [ns] (0 <= nanosec < 1e9).
int32 sec
uint32 nanosec
""",
    "std_msgs/msg/Header": """\
# When the data was acquired, and the frame it is expressed in.
builtin_interfaces/Time stamp
string frame_id
""",
    "std_msgs/msg/Bool": """\
bool data
""",
    "geometry_msgs/msg/Vector3": """\
float64 x
float64 y
float64 z
""",
    "geometry_msgs/msg/Point": """\
float64 x
float64 y
float64 z
""",
    "geometry_msgs/msg/Quaternion": """\
# Unit quaternion (x, y, z, w); the default is the identity rotation.
float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    "geometry_msgs/msg/Pose": """\
# Position [m] and orientation of a frame.
Point position
Quaternion orientation
""",
    "geometry_msgs/msg/PoseStamped": """\
std_msgs/Header header
Pose pose
""",
    "geometry_msgs/msg/PoseArray": """\
# Several poses, all expressed in header.frame_id.
std_msgs/Header header
Pose[] poses
""",
    "geometry_msgs/msg/Transform": """\
# Translation [m] and rotation of child_frame_id in the parent frame.
Vector3 translation
Quaternion rotation
""",
    "geometry_msgs/msg/TransformStamped": """\
# header.frame_id is the parent frame; child_frame_id the frame being placed.
std_msgs/Header header
string child_frame_id
Transform transform
""",
    "geometry_msgs/msg/Wrench": """\
# Force [N] and torque [N m].
Vector3 force
Vector3 torque
""",
    "geometry_msgs/msg/WrenchStamped": """\
std_msgs/Header header
Wrench wrench
""",
    "tf2_msgs/msg/TFMessage": """\
geometry_msgs/TransformStamped[] transforms
""",
    "sensor_msgs/msg/Image": """\
# Uncompressed image; header.frame_id is the camera's optical frame.
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
""",
    "sensor_msgs/msg/CompressedImage": """\
# Compressed image; format names the codec (e.g. png, jpeg).
std_msgs/Header header
string format
uint8[] data
""",
    "sensor_msgs/msg/RegionOfInterest": """\
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
""",
    "sensor_msgs/msg/CameraInfo": """\
# Calibration of a pinhole camera: intrinsics k [px], distortion d, rectification r,
# projection p.
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
""",
    "builtin_interfaces/msg/Duration": """\
int32 sec
uint32 nanosec
""",
    "std_msgs/msg/ColorRGBA": """\
float32 r
float32 g
float32 b
float32 a
""",
    "visualization_msgs/msg/UVCoordinate": """\
float32 u
float32 v
""",
    "visualization_msgs/msg/MeshFile": """\
string filename
uint8[] data
""",
    "visualization_msgs/msg/Marker": """\
# A shape for RViz / Foxglove / Lichtblick 3D views (the Humble definition). mvtop writes
# TRIANGLE_LIST markers: points are triangle corners [m] in header.frame_id, three per triangle.
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
visualization_msgs/UVCoordinate[] uv_coordinates
string text
string mesh_resource
visualization_msgs/MeshFile mesh_file
bool mesh_use_embedded_materials
""",
    "sensor_msgs/msg/JointState": """\
# Joint names with position [m or rad], velocity and effort; arrays may be empty.
std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
""",
}

MESSAGE_TYPES: tuple[str, ...] = tuple(sorted(_OWN_TEXT))
"""Every type whose definition this module provides, as ``pkg/msg/Name``."""

_PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)
# The separator rosbag2 (and ROS 1 before it) puts between concatenated definitions.
_SEPARATOR = "=" * 80


def normalize_type(type_name: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    parts = type_name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return type_name.strip()


def _short(type_name: str) -> str:
    pkg, _, name = normalize_type(type_name).split("/")
    return f"{pkg}/{name}"


def _field_types(type_name: str) -> list[str]:
    """The non-primitive field types of ``type_name`` in field order, as ``pkg/msg/Name``."""
    pkg = type_name.split("/")[0]
    out = []
    for line in _OWN_TEXT[type_name].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        base = re.sub(r"\[.*\]$", "", line.split()[0])
        base = re.sub(r"<=\d+$", "", base)
        if base in _PRIMITIVES:
            continue
        out.append(normalize_type(base if "/" in base else f"{pkg}/{base}"))
    return out


def dependencies(type_name: str) -> list[str]:
    """All types ``type_name`` depends on, each once, depth first in field order."""
    seen: list[str] = []

    def visit(name: str) -> None:
        for dep in _field_types(name):
            if dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(normalize_type(type_name))
    return seen


def definition(type_name: str) -> str:
    """The full ``ros2msg`` schema text of ``type_name`` as rosbag2 stores it.

    Raises KeyError for a type this module does not define (a programming error).
    """
    name = normalize_type(type_name)
    if name not in _OWN_TEXT:
        raise KeyError(f"no ROS 2 definition for {type_name!r}; known: {', '.join(MESSAGE_TYPES)}")
    text = _OWN_TEXT[name]
    for dep in dependencies(name):
        text += f"\n{_SEPARATOR}\nMSG: {_short(dep)}\n{_OWN_TEXT[dep]}"
    return text


_ALIASES = {"byte": "uint8", "char": "uint8"}


def _field_list(text: str, pkg: str) -> list[tuple[str, str]]:
    """``(type, name)`` of the fields in one ``.msg`` text (constants and comments dropped);
    non-primitive types are qualified with ``pkg`` and written ``pkg/Name``, array suffixes kept."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or "=" in line:  # blank, comment, or a constant
            continue
        parts = line.split()
        if len(parts) < 2:
            out.append((parts[0], ""))  # malformed: a type without a name
            continue
        type_text, name = parts[0], parts[1]
        m = re.match(r"^([^\[]+)(\[.*\])?$", type_text)
        base, suffix = (m.group(1), m.group(2) or "") if m else (type_text, "")
        base = _ALIASES.get(base, base)
        if re.sub(r"<=\d+$", "", base) not in _PRIMITIVES:
            base = _short(base if "/" in base else f"{pkg}/{base}") if base.count("/") in (0, 1, 2) else base
        out.append((base + suffix, name))
    return out


def schema_sections(type_name: str, text: str) -> dict[str, list[tuple[str, str]]]:
    """The field lists of a stored ``ros2msg`` schema text, keyed ``pkg/msg/Name``: the
    first section is ``type_name`` itself, the others are introduced by ``MSG: pkg/Name``."""
    sections: dict[str, list[tuple[str, str]]] = {}
    name, lines = normalize_type(type_name), []
    for line in text.splitlines() + [_SEPARATOR]:
        if line.strip() == _SEPARATOR:
            if name is not None:
                sections.setdefault(name, _field_list("\n".join(lines), name.split("/")[0]))
            name, lines = None, []
        elif name is None and line.startswith("MSG:"):
            name = normalize_type(line[4:].strip())
        elif name is not None:
            lines.append(line)
    return sections


def schema_mismatch(type_name: str, text: str) -> str | None:
    """Why a stored schema of ``type_name`` (a type this module defines) cannot be read as
    mvtop reads it, or None when every field mvtop knows is there with the same type
    (extra fields and comments are fine). Only the fields' names and types are compared."""
    name = normalize_type(type_name)
    stored = schema_sections(name, text)
    for t in [name, *dependencies(name)]:
        fields = stored.get(t)
        if fields is None:
            return f"has no definition of {t}"
        have = dict((n, ty) for ty, n in fields)
        for ty, n in _field_list(_OWN_TEXT[t], t.split("/")[0]):
            if n not in have:
                return f"lacks the field {n!r} of {t}"
            if have[n] != ty:
                return f"declares the field {n!r} of {t} as {have[n]!r} (expected {ty!r})"
    return None


# Shorthand constants for the types mvtop's topic layout uses.
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
JOINT_STATE = "sensor_msgs/msg/JointState"
BOOL = "std_msgs/msg/Bool"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
MARKER = "visualization_msgs/msg/Marker"
