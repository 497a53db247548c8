"""The reference renderer: pyrender (OpenGL over EGL), one depth render per pose.

Slow but independent of the numba rasteriser; tests hold the fast renderer to it. The scene
frame is the sensor's optical frame (x right, y down, z forward); OpenGL's camera looks down
its -z with y up, so the camera node sits at ``diag(1, -1, -1, 1)``. pyrender samples pixel
``(r, c)`` at ``(u, v) = (c + 0.5, r + 0.5)`` of the principal point it is given, so it gets
``cx + 0.5, cy + 0.5`` to sample pixel centres as OpenCV (and :class:`Roi`) define them.
pyrender renders into a 4x multisampled buffer and its depth read-back keeps one sample,
off the pixel centre (by (-1/8, +3/8) px on Mesa llvmpipe); the ``SEG`` flag turns
multisampling off, so renders use ``DEPTH_ONLY | SEG`` with every node in the segmentation
map. pyrender culls back faces in depth-only passes whatever the material says, so every
face is also drawn with reversed winding: double-sided, the truth for any winding.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render.base import DEFAULT_ZNEAR_M, Occluder, RendererBase, RenderMode
from mvtop_cli.render.gl import import_pyrender, offscreen_renderer
from mvtop_cli.render.roi import Roi

_T_OPTICAL_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _import_pyrender():
    return import_pyrender()


class PyrenderMaskRenderer(RendererBase):
    """:class:`~mvtop_cli.render.base.MaskRenderer` rendering each pose with pyrender
    (``DEPTH_ONLY``), in the ROI intrinsics of :meth:`Roi.camera`.

    zfar_m : far clipping distance [m]; depth precision degrades as ``zfar / znear`` grows
    """

    def __init__(self, znear_m: float = DEFAULT_ZNEAR_M, zfar_m: float = 10.0) -> None:
        super().__init__(znear_m)
        if not zfar_m > znear_m:
            raise ValueError(f"zfar_m {zfar_m} must exceed znear_m {znear_m}")
        self.zfar_m = float(zfar_m)
        self._pyrender = _import_pyrender()
        self._gl_meshes: dict[str, object] = {}
        self._renderer = None

    def add_mesh(self, mesh_id: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        super().add_mesh(mesh_id, vertices, faces)
        m = self.mesh(mesh_id)
        pr = self._pyrender
        faces = np.concatenate([m.faces, m.faces[:, ::-1]], axis=0)
        prim = pr.Primitive(positions=m.vertices.astype(np.float32), indices=faces, mode=4)  # 4: triangles
        self._gl_meshes[mesh_id] = pr.Mesh(primitives=[prim])

    def close(self) -> None:
        """Forget the OpenGL renderer (the process-wide context stays; see ``render.gl``)."""
        self._renderer = None

    def _offscreen(self, width: int, height: int):
        self._renderer = offscreen_renderer(width, height)
        return self._renderer

    def _depths(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None,
    ) -> np.ndarray:
        """Object depth (N, h, w) float32 [m], 0 where the object is absent or hidden."""
        pr = self._pyrender
        T = self._poses(T_sensor_object)
        self.mesh(mesh_id)
        occ = self._occluders(occluders)
        cam = roi.camera(camera)
        w, h = int(cam.width), int(cam.height)
        renderer = self._offscreen(w, h)
        scene = pr.Scene(bg_color=np.zeros(4), ambient_light=np.zeros(3))
        gl_cam = pr.IntrinsicsCamera(
            cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, znear=self.znear_m, zfar=self.zfar_m
        )
        scene.add(gl_cam, pose=_T_OPTICAL_GL)
        # SEG: single-sample rasterisation at pixel centres; nodes outside the map are skipped.
        flags = pr.RenderFlags.DEPTH_ONLY | pr.RenderFlags.SEG
        occ_depth = None
        if occ:
            nodes = [
                scene.add(self._gl_meshes[oid], pose=T_occ)
                for (oid, _), (_, T_occ) in zip(occluders or (), occ)
            ]
            occ_depth = renderer.render(scene, flags=flags, seg_node_map={n: 255 for n in nodes})
            for node in nodes:
                scene.remove_node(node)
        node = scene.add(self._gl_meshes[mesh_id], pose=np.eye(4))
        seg = {node: 255}
        out = np.empty((len(T), h, w), dtype=np.float32)
        for i, pose in enumerate(T):
            scene.set_pose(node, pose)
            d = renderer.render(scene, flags=flags, seg_node_map=seg)
            if occ_depth is not None:
                d = np.where((occ_depth > 0) & (occ_depth <= d), np.float32(0.0), d)
            out[i] = d
        blocked = self._blocked(occluders, camera, roi)
        if blocked is not None:
            out[:, blocked] = 0.0
        return out

    def render_masks(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
        mode: RenderMode = "silhouette",
        gel_distance_m: float | None = None,
        penetration_threshold_m: float = 0.0,
    ) -> np.ndarray:
        """Masks (N, h, w) bool of mesh ``mesh_id`` at poses ``T_sensor_object`` (N, 4, 4)."""
        plane = self._tactile_plane(mode, gel_distance_m, penetration_threshold_m)
        d = self._depths(mesh_id, T_sensor_object, camera, roi, occluders)
        if plane is None:
            return d > 0
        return (d > 0) & (d < plane)

    def render_depth(
        self,
        mesh_id: str,
        T_sensor_object: np.ndarray,
        camera: PinholeCamera,
        roi: Roi,
        occluders: Sequence[Occluder] | None = None,
    ) -> np.ndarray:
        """Depth z (N, h, w) float32 [m] of the object's nearest visible surface, ``inf``
        where the object is not seen."""
        d = self._depths(mesh_id, T_sensor_object, camera, roi, occluders)
        return np.where(d > 0, d, np.float32(np.inf)).astype(np.float32)
