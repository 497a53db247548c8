"""Static layout of the simulated work cell: table, fixture board, receptacle and two cameras.

Frames follow docs/frames.md: ``world`` z up with the table top at z = 0. Cameras are
RealSense-like 640 x 480 RGB cameras looking at the receptacle mouth from the front and the
side, 0.30-0.34 m away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..geometry import se3
from ..geometry.camera import PinholeCamera

BOARD_SIZE_M = (0.20, 0.15, 0.010)  # fixture board on the table [m]


@dataclass(frozen=True)
class CameraPlacement:
    """An external camera: name, optical frame in world, and intrinsics."""

    name: str
    T_world_camera: np.ndarray
    camera: PinholeCamera


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Optical frame (z forward, y down) at ``eye`` [m] looking at ``target`` [m], in world."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 0.0, -1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return se3.make_pose(np.stack([x, y, z], axis=1), eye)


def realsense_camera(width: int = 640, height: int = 480) -> PinholeCamera:
    """Intrinsics like a RealSense D435 colour stream (about 69 x 42 deg field of view), scaled
    to the requested resolution."""
    s = width / 640.0
    K = np.array([[615.0 * s, 0.0, 321.3 * s], [0.0, 615.0 * s, 238.6 * s], [0.0, 0.0, 1.0]])
    return PinholeCamera(width=width, height=height, K=K)


# Parts standing on each other are sunk this far into their support: coplanar faces would tie
# in the depth test, and pyrender's draw order (a Python set) would pick a different winner
# from run to run, breaking byte-identical logs.
SINK_M = 5e-4


def board_mesh() -> trimesh.Trimesh:
    """The fixture board in world (top face at z = BOARD_SIZE_M[2], bottom sunk into the table)."""
    sx, sy, sz = BOARD_SIZE_M
    box = trimesh.creation.box((sx, sy, sz + SINK_M))
    box.apply_translation([0.0, 0.0, (sz - SINK_M) / 2.0])
    return box


def table_mesh() -> trimesh.Trimesh:
    """A 1.2 x 0.8 m table slab in world, top face at z = 0."""
    box = trimesh.creation.box((1.2, 0.8, 0.04))
    box.apply_translation([0.0, 0.0, -0.02])
    return box


def receptacle_pose(receptacle: trimesh.Trimesh) -> np.ndarray:
    """``T_world_receptacle``: the receptacle stands on the board (sunk ``SINK_M`` into it),
    centred, mouth up."""
    z = BOARD_SIZE_M[2] - SINK_M - float(receptacle.bounds[0][2])
    return se3.make_pose(np.eye(3), [0.0, 0.0, z])


def camera_placements(target_world: np.ndarray, width: int = 640, height: int = 480) -> list[CameraPlacement]:
    """The front and side cameras, aimed at ``target_world`` [m] (a point above the receptacle)."""
    t = np.asarray(target_world, float)
    cam = realsense_camera(width, height)

    def eye(distance: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
        a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
        return t + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    return [
        # The fingers close along world y: both cameras look from the x sides, between the fingers.
        CameraPlacement("front", look_at(eye(0.30, -145.0, 30.0), t), cam),
        CameraPlacement("side", look_at(eye(0.34, -35.0, 24.0), t), cam),
    ]
