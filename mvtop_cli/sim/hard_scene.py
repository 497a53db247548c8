"""Harder simulated camera scenes: cluttered textured surroundings, glossy plastic, a
shadow-casting key light with dark faces, and lighting that changes from frame to frame.

Each part is an option of ``mvtop simulate`` (``SimulateOptions``: ``clutter``, ``glossy``,
``shadows``, ``light_change``); ``--scene hard`` turns them all on. Every random choice comes
from the generator passed in, so the same seed gives the same log. Distances are metres in the
world frame (table top at z = 0, the board centred at the origin, see ``sim.scene``).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..geometry import se3
from .camera_render import Material
from .scene import BOARD_SIZE_M, SINK_M

HARD_AMBIENT = 0.04  # ambient light with shadows: faces away from the key light stay dark
HARD_KEY_INTENSITY = 4.0  # key (directional) light [lux, pyrender]
HARD_FILL_INTENSITY = 0.3  # fill (point) light: weak, so shadows keep their contrast
GLOSSY_ROUGHNESS = 0.12  # polished plastic: sharp specular highlights
CLUTTER_ITEMS = 12  # boxes and cylinders standing around the board
CLUTTER_RADIUS_M = (0.13, 0.30)  # their distance from the receptacle
CLUTTER_HEIGHT_M = (0.01, 0.04)
TEXTURE_PX = 512


def textured_box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    """A box of ``extents`` [m] centred at ``centre`` [m] with its own four vertices per face, so
    a texture maps onto every face whole (UV 0-1 across each face)."""
    ex = np.asarray(extents, float) / 2.0
    verts, faces, uv = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            corners = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_ax], p[v_ax] = sign * ex[axis], du * ex[u_ax], dv * ex[v_ax]
                corners.append(p)
            base = len(verts)
            verts += corners
            uv += [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
            normal_ok = np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), np.eye(3)[axis] * sign) > 0
            tri = [(0, 1, 2), (0, 2, 3)] if normal_ok else [(0, 2, 1), (0, 3, 2)]
            faces += [(base + a, base + b, base + c) for a, b, c in tri]
    mesh = trimesh.Trimesh(np.asarray(verts) + np.asarray(centre, float), np.asarray(faces), process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv))
    return mesh


def clutter_texture(rng: np.random.Generator, size: int = TEXTURE_PX) -> np.ndarray:
    """A busy (size, size, 3) uint8 RGB texture: printed shapes, lines and grain in many colours,
    some close to the objects' own."""
    import cv2

    img = np.full((size, size, 3), rng.integers(60, 200, size=3), dtype=np.uint8)
    for _ in range(90):
        colour = tuple(int(c) for c in rng.integers(0, 256, size=3))
        kind = rng.integers(0, 3)
        x, y = (int(v) for v in rng.integers(0, size, size=2))
        r = int(rng.integers(6, size // 6))
        if kind == 0:
            cv2.rectangle(img, (x, y), (x + r, y + int(rng.integers(6, size // 6))), colour, -1)
        elif kind == 1:
            cv2.circle(img, (x, y), r // 2, colour, -1)
        else:
            x2, y2 = (int(v) for v in rng.integers(0, size, size=2))
            cv2.line(img, (x, y), (x2, y2), colour, int(rng.integers(1, 6)))
    grain = rng.normal(0.0, 12.0, size=(size, size, 1))
    return np.clip(img.astype(np.float64) + grain, 0, 255).astype(np.uint8)


def cluttered_parts(rng: np.random.Generator) -> dict[str, tuple[trimesh.Trimesh, Material]]:
    """The cluttered scene's table and board (textured, replacing the plain ones) and
    ``CLUTTER_ITEMS`` boxes and cylinders standing on the table around the board."""
    sx, sy, sz = BOARD_SIZE_M
    parts = {
        "table": (textured_box((1.2, 0.8, 0.04), (0.0, 0.0, -0.02)), Material((1.0, 1.0, 1.0), 0.0, 0.8,
                                                                              clutter_texture(rng))),
        "board": (textured_box((sx, sy, sz + SINK_M), (0.0, 0.0, (sz - SINK_M) / 2.0)),
                  Material((1.0, 1.0, 1.0), 0.0, 0.6, clutter_texture(rng))),
    }
    for i in range(CLUTTER_ITEMS):
        h = rng.uniform(*CLUTTER_HEIGHT_M)
        if rng.random() < 0.5:
            mesh = trimesh.creation.box((rng.uniform(0.015, 0.05), rng.uniform(0.015, 0.05), h + SINK_M))
        else:
            mesh = trimesh.creation.cylinder(radius=rng.uniform(0.008, 0.025), height=h + SINK_M, sections=24)
        r, a = rng.uniform(*CLUTTER_RADIUS_M), rng.uniform(0.0, 2.0 * np.pi)
        pose = se3.make_pose(se3.rotvec_to_matrix(np.array([0.0, 0.0, rng.uniform(0.0, np.pi)])),
                             [r * np.cos(a), r * np.sin(a), (h - SINK_M) / 2.0])
        mesh.apply_transform(pose)
        (x0, y0, _), (x1, y1, _) = mesh.bounds
        if x0 < sx / 2 and x1 > -sx / 2 and y0 < sy / 2 and y1 > -sy / 2:
            mesh.apply_translation([0.0, 0.0, sz])  # standing on the board, not in it
        colour = tuple(float(c) for c in rng.uniform(0.05, 0.95, size=3))
        parts[f"clutter{i}"] = (mesh, Material(colour, 0.0, float(rng.uniform(0.15, 0.9))))
    return parts


def glossy(material: Material) -> Material:
    """``material`` as polished plastic: the same colour, no metal, ``GLOSSY_ROUGHNESS``."""
    return Material(material.rgb, 0.0, GLOSSY_ROUGHNESS, material.texture)


def frame_lights(rng: np.random.Generator, T_world_key: np.ndarray, change: float,
                 key: float, fill: float) -> tuple[np.ndarray, float, float]:
    """The key light's pose and the key and fill intensities of one frame, changed from the
    nominal ``T_world_key``, ``key`` and ``fill`` by ``change`` (0: constant): the key turns by
    about ``change * 30`` deg and each intensity scales by ``exp(N(0, change))``."""
    if change <= 0:
        return T_world_key, key, fill
    turn = se3.make_pose(se3.rotvec_to_matrix(rng.normal(0.0, np.radians(30.0) * change, size=3)), np.zeros(3))
    return (turn @ T_world_key, key * float(np.exp(rng.normal(0.0, change))),
            fill * float(np.exp(rng.normal(0.0, change))))
