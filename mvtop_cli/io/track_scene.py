"""What makes track.mcap a self-contained scene in Foxglove / Lichtblick / RViz.

Beside the pose topics, ``write_track_scene`` adds

- ``/tf``: at every track stamp ``world -> ee`` (``T_world_ee = T_world_object
  T_ee_object^-1``, the end effector the estimate was made with) and ``world ->
  object_estimate`` (``T_world_object``), so ``/mvtop/object_pose_ee`` (in ``ee``) and
  ``object_estimate`` are placed without the recorded log. Opened beside the log, ``ee``
  has two parents (the log's chain and ``world`` here); both give the same pose, the one
  the estimate used;
- ``/mvtop/object_model``: the object's CAD model as a visualization_msgs/Marker
  TRIANGLE_LIST in ``object_estimate`` (frame-locked), written once at the first stamp: it
  stays until replaced, so the part is drawn at the estimate of every frame.

Frames and stamps are the track's; nothing here depends on the recorded log.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import se3
from .mcap_writer import LogWriter

OBJECT_FRAME = "object_estimate"
MODEL_TOPIC = "/mvtop/object_model"
MODEL_RGBA = (0.95, 0.55, 0.1, 0.9)  # orange: stands out against camera images and grey fixtures


def write_track_scene(
    w: LogWriter,
    stamps_ns: list[int],
    T_world_object: np.ndarray,
    T_ee_object: np.ndarray,
    triangles: np.ndarray,
    world_frame: str,
    ee_frame: str,
) -> None:
    """TF and the object model for a track (see the module doc).

    stamps_ns : N stamps [ns]; T_world_object, T_ee_object : (N, 4, 4) estimates;
    triangles : (k, 3, 3) the object's mesh triangles in its own frame [m].
    """
    T_world_object = np.asarray(T_world_object, dtype=np.float64).reshape(-1, 4, 4)
    T_ee_object = np.asarray(T_ee_object, dtype=np.float64).reshape(-1, 4, 4)
    T_world_ee = T_world_object @ se3.invert(T_ee_object)
    for i, stamp in enumerate(stamps_ns):
        if i == 0:
            w.write_triangle_marker(MODEL_TOPIC, triangles, int(stamp), OBJECT_FRAME, rgba=MODEL_RGBA, ns="object")
        w.write_tf([(world_frame, ee_frame, T_world_ee[i]), (world_frame, OBJECT_FRAME, T_world_object[i])], int(stamp))


def object_triangles(mesh_path: str | Path, units: str = "m") -> np.ndarray:
    """The object mesh as triangles (k, 3, 3) in metres, in the object frame."""
    from .meshes import load_mesh

    mesh = load_mesh(mesh_path, units, what="object mesh")
    return np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
