"""What the estimator knows of the scene, built once from a config: meshes registered in the
mask renderer, environment occluders, and the environment's signed distance for contact."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..config import Config, EnvironmentMesh
from ..contact.sdf import ObjectSignedDistance
from ..errors import MeshError
from ..geometry import se3
from ..io.meshes import load_mesh
from ..render.numba_renderer import NumbaMaskRenderer

OBJECT_ID = "object"
_MAX_OBJECT_EXTENT_M = 1.0  # larger than any part a gripper holds: a unit error (mm as m)
_MIN_OBJECT_EXTENT_M = 5e-4  # smaller than any part: a unit error the other way (m as mm)


@dataclass(frozen=True)
class EnvPart:
    """An environment mesh: its config entry and its pose in its TF frame."""

    spec: EnvironmentMesh
    mesh: trimesh.Trimesh
    T_frame_mesh: np.ndarray


class SceneModel:
    """Object and environment geometry for rendering and contact, from a validated config."""

    def __init__(self, cfg: Config, build_contact: bool = True):
        self.cfg = cfg
        self.object_mesh = load_mesh(cfg.object.mesh, cfg.object.units, "object mesh")
        extent = float(np.max(self.object_mesh.extents))
        if extent > _MAX_OBJECT_EXTENT_M or extent < _MIN_OBJECT_EXTENT_M:
            hint = "mm" if extent > _MAX_OBJECT_EXTENT_M else "m"
            raise MeshError(
                f"{cfg.object.mesh}: object is {extent:g} m across with units {cfg.object.units!r}; "
                f"a hand-held part is 0.5 mm to 1 m (are the units {hint!r}?)"
            )
        self.renderer = NumbaMaskRenderer()
        self.renderer.add_mesh(OBJECT_ID, self.object_mesh.vertices, self.object_mesh.faces)
        self.parts: list[EnvPart] = []
        for e in cfg.environment:
            mesh = load_mesh(e.mesh, e.units, f"environment mesh {e.name!r}")
            self.parts.append(EnvPart(e, mesh, e.pose.matrix()))
            if e.occlude:
                self.renderer.add_mesh(f"env:{e.name}", mesh.vertices, mesh.faces)
        self.symmetries = np.stack([np.eye(4)] + [s.matrix() for s in cfg.object.symmetries])
        self.sdf: ObjectSignedDistance | None = None
        if build_contact:
            self._build_contact()

    def _build_contact(self) -> None:
        """Signed-distance grid of the world-fixed environment meshes around the receptacle."""
        fixed = [p for p in self.parts if p.spec.collide and p.spec.frame == self.cfg.frames.world]
        if not fixed:
            return
        meshes = [p.mesh for p in fixed]
        poses = np.stack([p.T_frame_mesh for p in fixed])
        # The grid covers the receptacle-sized fixed parts (under 10 cm: receptacles, fixtures,
        # not the board or table they stand on, whose top face inside the box is still in the
        # grid) with a 5 mm margin: contact happens there; farther out phi is only needed to be
        # large, and the grid's continuation beyond its box (value + distance) gives that.
        boxes = [trimesh.transformations.transform_points(m.bounds, T) for m, T in zip(meshes, poses)]
        small = [b for b in boxes if np.max(b.max(axis=0) - b.min(axis=0)) < 0.1] or boxes
        lo = np.min([b.min(axis=0) for b in small], axis=0)
        hi = np.max([b.max(axis=0) for b in small], axis=0)
        margin = 0.005
        bounds = np.stack([lo - margin, hi + margin])
        res = self.cfg.contact.sdf_resolution_m
        cells = np.prod((bounds[1] - bounds[0]) / res)
        if cells > 2e7:  # keep the grid under ~80 MB of float32 and a few seconds to build
            res = float(((bounds[1] - bounds[0]).prod() / 2e7) ** (1 / 3))
        self.sdf = ObjectSignedDistance.from_meshes(
            self.object_mesh, meshes, poses, bounds, rng=np.random.default_rng(0), resolution_m=res,
            n_points=1000, use_fcl=False,
        )

    @property
    def has_contact_model(self) -> bool:
        return self.sdf is not None

    def phi(self, T_world_object: np.ndarray) -> np.ndarray:
        """Signed distance (N,) [m] between the object at poses (N, 4, 4) and the fixed
        environment near the receptacle; negative when penetrating (eq. 8's phi). Far from
        the grid (beyond one object size) it over-estimates, which only lowers a contact
        weight that is already negligible there."""
        if self.sdf is None:
            raise RuntimeError("no contact model: the config has no world-fixed environment mesh")
        return self.sdf.phi_grid(T_world_object)

    def occluders(self, T_world_sensor: np.ndarray, frame_pose) -> list[tuple[str, np.ndarray]]:
        """Occluder meshes ``(mesh_id, T_sensor_mesh)`` for one camera; ``frame_pose(name)``
        returns ``T_world_frame`` of a TF frame at the image time."""
        T_sensor_world = se3.invert(T_world_sensor)
        out = []
        for p in self.parts:
            if not p.spec.occlude:
                continue
            T_world_frame = np.eye(4) if p.spec.frame == self.cfg.frames.world else frame_pose(p.spec.frame)
            out.append((f"env:{p.spec.name}", T_sensor_world @ T_world_frame @ p.T_frame_mesh))
        return out
