"""The camera pixels where the part meets a surface it rests on (``masking.contact_exclusion_m``).

Where a part touches a receptacle of its own colour the image shows no outline between them, and
a camera mask takes in the receptacle, or leaves out the part, by chance. These pixels are found
from geometry that holds no belief: the box the grasp prior's fixed poses span (in the end
effector's frame, moved with it), widened by a margin, and the world-fixed colliding environment
meshes rendered into the camera. A pixel is a contact pixel when the nearest surface it shows is
such a mesh and that surface point lies in the box. Whether they are excluded in a frame is the
observation model's choice (``ObservationModel.contact_pixels``: only where the surface there
shows the part's colours).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..geometry import se3
from ..records import SensorImage
from ..render.roi import Roi
from .scene import SceneModel


def prior_box(object_bounds: np.ndarray, T_world_object: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo (3,), hi (3,)) [m] in ``world``: the axis-aligned box of the object's bounding box
    ``object_bounds`` (2, 3) [m, object frame] at every pose of ``T_world_object`` (N, 4, 4),
    widened by ``margin_m`` on every side."""
    pts = se3.transform_points(T_world_object, trimesh.bounds.corners(object_bounds)).reshape(-1, 3)
    return pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m


def _boxes_overlap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    return bool(np.all(a[0] <= b[1]) and np.all(b[0] <= a[1]))


def _box_window(img: SensorImage, box: tuple[np.ndarray, np.ndarray]) -> Roi | None:
    """The image window (full resolution) the box projects to; the whole image when the box
    reaches behind the camera; None when it projects outside the image."""
    cam = img.camera
    p_sensor = se3.transform_points(se3.invert(img.T_world_sensor), trimesh.bounds.corners(np.array(box)))
    if not np.all(p_sensor[:, 2] > 1e-3):
        return Roi.full(cam)
    uv = cam.project(p_sensor)
    x0, y0 = max(int(np.floor(uv[:, 0].min())) - 1, 0), max(int(np.floor(uv[:, 1].min())) - 1, 0)
    x1 = min(int(np.ceil(uv[:, 0].max())) + 2, cam.width)
    y1 = min(int(np.ceil(uv[:, 1].max())) + 2, cam.height)
    if x1 <= x0 or y1 <= y0:
        return None
    return Roi(x0, y0, x1 - x0, y1 - y0)


def surface_pixels_in_box(scene: SceneModel, img: SensorImage, occluders: list,
                          box: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """The pixels (H, W) bool of camera image ``img`` whose nearest surface, among the
    ``occluders`` (``(mesh_id, T_sensor_mesh)`` of the environment), is a world-fixed colliding
    mesh at a point inside ``box`` (lo, hi) [m, world]; None when there is none."""
    world = scene.cfg.frames.world
    touched = {f"env:{p.spec.name}" for p in scene.parts
               if p.spec.collide and p.spec.occlude and p.spec.frame == world and _boxes_overlap(p.world_bounds, box)}
    roi = _box_window(img, box) if touched else None
    if roi is None:
        return None
    cam = img.camera
    nearest = np.full(roi.shape, np.inf, dtype=np.float32)
    nearest_touched = np.full(roi.shape, np.inf, dtype=np.float32)
    for mesh_id, T_sensor_mesh in occluders:
        depth = scene.renderer.render_depth(mesh_id, T_sensor_mesh[None], cam, roi)[0]
        np.minimum(nearest, depth, out=nearest)
        if mesh_id in touched:
            np.minimum(nearest_touched, depth, out=nearest_touched)
    rows, cols = np.nonzero(np.isfinite(nearest_touched) & (nearest_touched <= nearest))
    z = nearest_touched[rows, cols].astype(np.float64)
    xyz = np.stack([(cols + roi.x0 - cam.cx) / cam.fx * z, (rows + roi.y0 - cam.cy) / cam.fy * z, z], axis=1)
    p_world = se3.transform_points(img.T_world_sensor, xyz)
    inside = np.all((p_world >= box[0]) & (p_world <= box[1]), axis=1)
    if not inside.any():
        return None
    out = np.zeros((cam.height, cam.width), dtype=bool)
    out[rows[inside] + roi.y0, cols[inside] + roi.x0] = True
    return out
