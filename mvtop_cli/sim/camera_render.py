"""Photometric rendering of the external RGB cameras with pyrender (EGL, offscreen).

Each simulated frame renders the full scene (table, board, receptacle, fingers, object and any
extra occluders) with materials and lights, then applies exposure, sensor noise and blur.
Harder scenes (``shadows``) let the key light cast shadows and dim the ambient light, so faces
turned away from the key light stay dark; materials may carry a texture (cluttered scenes).
The object's visible pixels come from the same depth buffer, for tests and debugging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..geometry.camera import PinholeCamera
from ..render.gl import import_pyrender, offscreen_renderer

GL_FROM_OPTICAL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL camera (y up, looks down -z) in optical


def pyrender_intrinsics(pyrender, camera: PinholeCamera, znear: float = 0.005, zfar: float = 5.0):
    """A pyrender camera equal to ``camera``. pyrender puts pixel centres at +0.5 (OpenGL),
    OpenCV at integers, hence the half-pixel shift of the principal point."""
    return pyrender.IntrinsicsCamera(
        fx=camera.fx, fy=camera.fy, cx=camera.cx + 0.5, cy=camera.cy + 0.5, znear=znear, zfar=zfar
    )


@dataclass(frozen=True)
class Material:
    """Base colour (RGB 0-1), metalness and roughness of a simulated part; ``texture`` an
    optional (H, W, 3) uint8 RGB image multiplied into the colour (the mesh needs UV coordinates,
    ``trimesh.visual.TextureVisuals``)."""

    rgb: tuple[float, float, float]
    metallic: float = 0.0
    roughness: float = 0.7
    texture: np.ndarray | None = None


@dataclass(frozen=True)
class PhotometricOptions:
    """Camera effects: exposure gain, Gaussian read noise [DN of 255], blur sigma [px]."""

    exposure: float = 1.0
    noise_std: float = 2.0
    blur_px: float = 0.6


class CameraSceneRenderer:
    """Renders RGB images of a set of named meshes whose poses change per frame."""

    def __init__(self, meshes: dict[str, tuple[trimesh.Trimesh, Material]], width: int, height: int,
                 shadows: bool = False, ambient: float = 0.25):
        """Renders ``meshes`` (name -> mesh, material) at ``width`` x ``height`` through the
        process's shared offscreen context (``render.gl``); ``shadows``: the key (directional)
        light casts shadows; ``ambient`` the ambient light level (0-1)."""
        pr = import_pyrender()
        self._pr = pr
        self.shadows = shadows
        self.scene = pr.Scene(bg_color=[0.55, 0.58, 0.62, 1.0], ambient_light=[ambient] * 3)
        self.nodes: dict[str, object] = {}
        # pyrender draws opaque meshes sorted by the distance of their node origin from the
        # camera, ties in the order of a Python set; so each mesh is recentred on its bounding
        # box centre (folded back into the node pose) to make the draw order, and with it any
        # depth-test tie, the same in every run.
        self._centre: dict[str, np.ndarray] = {}
        for name, (mesh, mat) in meshes.items():
            texture = None if mat.texture is None else pr.Texture(source=mat.texture, source_channels="RGB")
            material = pr.MetallicRoughnessMaterial(
                baseColorFactor=[*mat.rgb, 1.0], metallicFactor=mat.metallic, roughnessFactor=mat.roughness,
                baseColorTexture=texture,
            )
            centre = np.asarray(mesh.bounds, dtype=float).mean(axis=0)
            self._centre[name] = centre
            mesh = mesh.copy()
            mesh.apply_translation(-centre)
            pm = pr.Mesh.from_trimesh(mesh, material=material, smooth=False)
            self.nodes[name] = self.scene.add(pm, pose=np.eye(4), name=name)
            self.set_pose(name, np.eye(4))
        self._key = self.scene.add(pr.DirectionalLight(color=np.ones(3), intensity=3.0), pose=np.eye(4))
        self._fill = self.scene.add(pr.PointLight(color=np.ones(3), intensity=1.5), pose=np.eye(4))
        self._cam_node = None
        self.width, self.height = width, height

    def set_pose(self, name: str, T_world_mesh: np.ndarray) -> None:
        T = np.asarray(T_world_mesh, dtype=float).copy()
        T[:3, 3] += T[:3, :3] @ self._centre[name]
        self.scene.set_pose(self.nodes[name], pose=T)

    def set_lights(
        self, T_world_key: np.ndarray, fill_position: np.ndarray, key_intensity: float, fill_intensity: float
    ) -> None:
        self.scene.set_pose(self._key, pose=T_world_key)
        T = np.eye(4)
        T[:3, 3] = fill_position
        self.scene.set_pose(self._fill, pose=T)
        self._key.light.intensity = key_intensity
        self._fill.light.intensity = fill_intensity

    def _set_camera(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> None:
        self.renderer = offscreen_renderer(self.width, self.height)
        if self._cam_node is not None:
            self.scene.remove_node(self._cam_node)
        cam = pyrender_intrinsics(self._pr, camera)
        self._cam_node = self.scene.add(cam, pose=np.asarray(T_world_camera) @ GL_FROM_OPTICAL)

    def render(self, camera: PinholeCamera, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear RGB (H, W, 3) float in [0, 1] and depth (H, W) [m] (0 = background)."""
        self._set_camera(camera, T_world_camera)
        if self.shadows:
            color, depth = self.renderer.render(self.scene, flags=self._pr.RenderFlags.SHADOWS_DIRECTIONAL)
        else:
            color, depth = self.renderer.render(self.scene)
        return color.astype(np.float32) / 255.0, depth

    def render_depth_only(self, camera: PinholeCamera, T_world_camera: np.ndarray, only: str) -> np.ndarray:
        """Depth (H, W) [m] of the mesh ``only`` alone (0 = not covered), sampled at pixel centres."""
        self._set_camera(camera, T_world_camera)
        # SEG: one sample at each pixel centre, the OpenCV convention of ``camera``; a plain
        # depth render reads the multisampled buffer's first sample, about (-0.1, +0.4) px off
        return self.renderer.render(self.scene, flags=self._pr.RenderFlags.DEPTH_ONLY | self._pr.RenderFlags.SEG,
                                    seg_node_map={self.nodes[only]: 255})

    def visible_mask(self, camera: PinholeCamera, T_world_camera: np.ndarray, only: str) -> np.ndarray:
        """Pixels (H, W) bool where the mesh ``only`` is the nearest surface of the scene,
        sampled at pixel centres (the true object mask a perfect segmenter would give)."""
        self._set_camera(camera, T_world_camera)
        seg = {node: (255, 255, 255) if name == only else (1, 1, 1) for name, node in self.nodes.items()}
        colour, _ = self.renderer.render(self.scene, flags=self._pr.RenderFlags.SEG, seg_node_map=seg)
        return colour[..., 0] == 255

    def close(self) -> None:
        """Drop the scene (the shared context stays for the next renderer)."""
        self.scene.clear()


def apply_camera_effects(linear_rgb: np.ndarray, options: PhotometricOptions, rng: np.random.Generator) -> np.ndarray:
    """Exposure, optical blur, read noise and 8-bit quantisation of a rendered image."""
    import cv2

    img = np.clip(linear_rgb * options.exposure, 0.0, 1.0)
    if options.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), options.blur_px)
    img = img * 255.0 + rng.normal(0.0, options.noise_std, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
