"""The simulated robot as a real setup describes it: a Cartesian gantry with a 3-axis wrist.

Kinematic chain (every joint origin a pure translation, so the joint values follow from the
end-effector pose in closed form)::

    world -(static mount)-> base_link
      -(gantry_x_joint, prismatic x)-> gantry_x -(gantry_y_joint, prismatic y)-> gantry_y
      -(gantry_z_joint, prismatic z, origin GANTRY_HEIGHT_M up)-> gantry_z
      -(wrist_yaw_joint, revolute z)-> wrist_yaw -(wrist_pitch_joint, revolute y)-> wrist_pitch
      -(wrist_roll_joint, revolute x)-> flange
      -(fixed tool mount)-> tool0 -(fixed TCP offset)-> ee
      -(finger_left_joint / finger_right_joint, prismatic)-> finger_left / finger_right
      -(fixed)-> tactile_left_optical / tactile_right_optical

The wrist is a Z-Y-X Euler wrist, so ``T_base_flange = T(p) Rz(yaw) Ry(pitch) Rx(roll)`` up to
the constant link offsets; the tool mount is tilted so that all three wrist angles are away
from zero (and from the pitch singularity at +-90 deg) over the simulated episodes. Finger
joint values are each pad's distance from the TCP along ee y [m], their sum the opening.

Frames and units as everywhere in mvtop: ``T_a_b`` is frame ``b`` in frame ``a``, metres and
radians. :func:`urdf_text` writes the same robot as a URDF (what ``robot.urdf`` in a config
points to); :func:`link_transforms` gives its edges as TF would carry them.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import se3
from . import gripper as grip

ROBOT_NAME = "mvtop_gantry"
BASE_LINK = "base_link"
GANTRY_HEIGHT_M = 0.45  # gantry_z joint origin above base_link [m]
# Constant link offsets [m], each in its parent link's frame: the wrist hangs below the gantry.
WRIST_YAW_OFFSET_M = (0.0, 0.0, -0.08)
WRIST_PITCH_OFFSET_M = (0.0, 0.0, -0.06)
WRIST_ROLL_OFFSET_M = (0.02, 0.0, -0.05)
# Where the robot stands in the work cell: base_link 0.5 m to the side of the board, turned
# -90 deg about world z (so gantry x moves along world -y).
T_WORLD_BASE = se3.make_pose(Rotation.from_euler("z", -90.0, degrees=True).as_matrix(), [0.35, 0.40, 0.0])
# Tool changer on the flange, tilted 20 deg about the flange y axis and turned about its z,
# then the TCP 0.12 m out along the tool's z with the tool's z pointing down at the part.
T_FLANGE_TOOL = se3.make_pose(
    Rotation.from_euler("xyz", [180.0, 20.0, 35.0], degrees=True).as_matrix(), [0.0, 0.0, -0.03]
)
T_TOOL_EE = se3.make_pose(Rotation.from_euler("z", -12.0, degrees=True).as_matrix(), [0.004, -0.002, 0.12])
T_FLANGE_EE = T_FLANGE_TOOL @ T_TOOL_EE

ARM_JOINTS = (
    "gantry_x_joint", "gantry_y_joint", "gantry_z_joint", "wrist_yaw_joint", "wrist_pitch_joint", "wrist_roll_joint",
)
FINGER_JOINTS = ("finger_left_joint", "finger_right_joint")
# Dynamic edges (parent, child) of the arm, in chain order, each moved by ARM_JOINTS[i].
ARM_EDGES = (
    (BASE_LINK, "gantry_x"), ("gantry_x", "gantry_y"), ("gantry_y", "gantry_z"),
    ("gantry_z", "wrist_yaw"), ("wrist_yaw", "wrist_pitch"), ("wrist_pitch", "flange"),
)


def _trans(xyz) -> np.ndarray:
    return se3.make_pose(np.eye(3), np.asarray(xyz, dtype=np.float64))


def _rot(axis: str, angle_rad: float) -> np.ndarray:
    return se3.make_pose(Rotation.from_euler(axis, float(angle_rad)).as_matrix(), np.zeros(3))


def inverse_kinematics(T_world_ee: np.ndarray) -> np.ndarray:
    """Joint values (6,) of ARM_JOINTS (3 gantry positions [m], yaw, pitch, roll [rad]) that
    put ``ee`` at ``T_world_ee`` (4, 4) exactly (closed form, no iteration)."""
    T_base_flange = se3.invert(T_WORLD_BASE) @ np.asarray(T_world_ee, dtype=np.float64) @ se3.invert(T_FLANGE_EE)
    yaw, pitch, roll = Rotation.from_matrix(T_base_flange[:3, :3]).as_euler("ZYX")
    Rz = Rotation.from_euler("z", yaw).as_matrix()
    Rzy = Rz @ Rotation.from_euler("y", pitch).as_matrix()
    p = (T_base_flange[:3, 3] - np.asarray(WRIST_YAW_OFFSET_M) - Rz @ np.asarray(WRIST_PITCH_OFFSET_M)
         - Rzy @ np.asarray(WRIST_ROLL_OFFSET_M) - np.array([0.0, 0.0, GANTRY_HEIGHT_M]))
    return np.array([p[0], p[1], p[2], yaw, pitch, roll])


def arm_transforms(q: np.ndarray) -> list[tuple[str, str, np.ndarray]]:
    """The moving edges ``(parent, child, T_parent_child)`` of ARM_EDGES for joint values ``q`` (6,)."""
    x, y, z, yaw, pitch, roll = (float(v) for v in q)
    return [
        (BASE_LINK, "gantry_x", _trans([x, 0.0, 0.0])),
        ("gantry_x", "gantry_y", _trans([0.0, y, 0.0])),
        ("gantry_y", "gantry_z", _trans([0.0, 0.0, GANTRY_HEIGHT_M + z])),
        ("gantry_z", "wrist_yaw", _trans(WRIST_YAW_OFFSET_M) @ _rot("z", yaw)),
        ("wrist_yaw", "wrist_pitch", _trans(WRIST_PITCH_OFFSET_M) @ _rot("y", pitch)),
        ("wrist_pitch", "flange", _trans(WRIST_ROLL_OFFSET_M) @ _rot("x", roll)),
    ]


def forward_kinematics(q: np.ndarray) -> np.ndarray:
    """``T_world_ee`` (4, 4) for arm joint values ``q`` (6,)."""
    T = T_WORLD_BASE.copy()
    for _parent, _child, T_pc in arm_transforms(q):
        T = T @ T_pc
    return T @ T_FLANGE_EE


def static_transforms() -> list[tuple[str, str, np.ndarray]]:
    """The fixed edges of the arm as static TF would carry them: the base mount in world, the
    tool mount on the flange and the TCP on the tool (the finger-to-tactile mounts are the
    simulator's usual static transforms)."""
    return [("world", BASE_LINK, T_WORLD_BASE), ("flange", "tool0", T_FLANGE_TOOL), ("tool0", "ee", T_TOOL_EE)]


def finger_joint_values(pad_left_y_m: float, pad_right_y_m: float) -> list[float]:
    """Positions [m] of FINGER_JOINTS: each pad's distance from the TCP along ee y."""
    return [float(pad_left_y_m), float(-pad_right_y_m)]


def _origin(T: np.ndarray) -> str:
    # URDF rpy: fixed-axis roll, pitch, yaw, R = Rz(yaw) Ry(pitch) Rx(roll); repr() keeps every
    # bit of the float so the file reproduces the simulator's poses to rounding.
    rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
    xyz = " ".join(repr(float(v) + 0.0) for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{" ".join(repr(float(v) + 0.0) for v in rpy)}"/>'


def urdf_text(gel_distance_m: float = 0.025) -> str:
    """The robot as a URDF document (kinematics only, no meshes): what a real setup's robot
    description would give, with the tactile sensors' optical frames ``gel_distance_m`` [m]
    behind their gel pads."""
    fingers = grip.finger_poses(0.0)
    T_finger_tac = grip.T_finger_tactile_optical(gel_distance_m)
    big = 'effort="100" velocity="1"'
    lines = ['<?xml version="1.0"?>', f'<robot name="{ROBOT_NAME}">']
    links = [BASE_LINK] + [c for _p, c in ARM_EDGES] + ["tool0", "ee", "finger_left", "finger_right",
                                                          "tactile_left_optical", "tactile_right_optical"]
    lines += [f'  <link name="{name}"/>' for name in links]
    arm = [
        ("gantry_x_joint", "prismatic", _trans([0, 0, 0]), "1 0 0", '<limit lower="-2" upper="2" ' + big + "/>"),
        ("gantry_y_joint", "prismatic", _trans([0, 0, 0]), "0 1 0", '<limit lower="-2" upper="2" ' + big + "/>"),
        ("gantry_z_joint", "prismatic", _trans([0, 0, GANTRY_HEIGHT_M]), "0 0 1",
         '<limit lower="-1" upper="1" ' + big + "/>"),
        ("wrist_yaw_joint", "revolute", _trans(WRIST_YAW_OFFSET_M), "0 0 1",
         '<limit lower="-3.2" upper="3.2" ' + big + "/>"),
        ("wrist_pitch_joint", "revolute", _trans(WRIST_PITCH_OFFSET_M), "0 1 0",
         '<limit lower="-1.5" upper="1.5" ' + big + "/>"),
        ("wrist_roll_joint", "revolute", _trans(WRIST_ROLL_OFFSET_M), "1 0 0",
         '<limit lower="-3.2" upper="3.2" ' + big + "/>"),
    ]
    for (name, kind, T, axis, limit), (parent, child) in zip(arm, ARM_EDGES):
        lines += [f'  <joint name="{name}" type="{kind}">', f'    <parent link="{parent}"/>',
                  f'    <child link="{child}"/>',
                  f"    {_origin(T)}", f'    <axis xyz="{axis}"/>', f"    {limit}", "  </joint>"]
    fixed = [("tool_mount", "flange", "tool0", T_FLANGE_TOOL), ("tcp", "tool0", "ee", T_TOOL_EE),
             ("tactile_left_mount", "finger_left", "tactile_left_optical", T_finger_tac),
             ("tactile_right_mount", "finger_right", "tactile_right_optical", T_finger_tac)]
    for name, parent, child, T in fixed:
        lines += [f'  <joint name="{name}" type="fixed">', f'    <parent link="{parent}"/>',
                  f'    <child link="{child}"/>',
                  f"    {_origin(T)}", "  </joint>"]
    # Each finger slides along its own -z (away from the part, i.e. along ee +-y), so a joint
    # value q puts its pad q from the TCP: T_ee_finger = R_finger @ T(-q z).
    for side, joint in zip(grip.FINGERS, FINGER_JOINTS):
        lines += [f'  <joint name="{joint}" type="prismatic">', '    <parent link="ee"/>',
                  f'    <child link="finger_{side}"/>', f"    {_origin(fingers[side])}", '    <axis xyz="0 0 -1"/>',
                  '    <limit lower="0" upper="0.05" ' + big + "/>", "  </joint>"]
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
