"""What the estimator knows of the scene, built once from a config: meshes registered in the
mask renderer, environment occluders, and the environment's signed distance for contact.

Meshes are checked as they are loaded: those whose inside matters (the object with the tactile
or contact modality, the world-fixed colliding meshes of the contact model) must be
watertight, after repair if needed; every mesh's size must fit its declared units."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..config import Config, EnvironmentMesh
from ..contact.grid import contact_grid
from ..contact.sdf import ObjectSignedDistance
from ..errors import MeshError
from ..filter.health import warning
from ..geometry import se3
from ..io.cache import cache_dir
from ..io.meshes import load_mesh
from ..render.numba_renderer import NumbaMaskRenderer

OBJECT_ID = "object"
_MAX_OBJECT_EXTENT_M = 1.0  # larger than any part a gripper holds: a unit error (mm as m)
_MIN_OBJECT_EXTENT_M = 5e-4  # smaller than any part: a unit error the other way (m as mm)
_MAX_ENVIRONMENT_EXTENT_M = 20.0  # larger than any work cell
# An object more than this many times the size of the gripper-mounted meshes (fingers) is
# suspicious but possible (a long rod); the 1000x of a unit error is far beyond it.
_MAX_OBJECT_TO_GRIPPER = 10.0
_MIN_OBJECT_TO_GRIPPER = 0.02


@dataclass(frozen=True)
class EnvPart:
    """An environment mesh: its config entry and its pose in its TF frame."""

    spec: EnvironmentMesh
    mesh: trimesh.Trimesh
    T_frame_mesh: np.ndarray

    @property
    def world_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo (3,), hi (3,)) [m]: the axis-aligned box of the mesh in its TF frame (``world``
        for a fixed part)."""
        corners = trimesh.transformations.transform_points(trimesh.bounds.corners(self.mesh.bounds), self.T_frame_mesh)
        return corners.min(axis=0), corners.max(axis=0)


class SceneModel:
    """Object and environment geometry for rendering and contact, from a validated config."""

    def __init__(self, cfg: Config, build_contact: bool = True):
        self.cfg = cfg
        # warnings about the scene (filter.health records, frame None): repaired meshes, units
        self.warnings: list[dict] = []
        notes: list[str] = []
        object_closed = bool({"tactile", "contact"} & set(cfg.modalities))
        self.object_mesh = load_mesh(
            cfg.object.mesh, cfg.object.units, "object mesh", closed=object_closed, notes=notes
        )
        _check_size(self.object_mesh, cfg.object.mesh, "object.units", cfg.object.units,
                    _MIN_OBJECT_EXTENT_M, _MAX_OBJECT_EXTENT_M, "a part held in a gripper")
        self.renderer = NumbaMaskRenderer()
        shown = self.object_mesh if cfg.object.render_mesh is None else load_mesh(
            cfg.object.render_mesh, cfg.object.units, "object render mesh")  # a simplified copy (mesh-check)
        self.renderer.add_mesh(OBJECT_ID, shown.vertices, shown.faces)
        self.parts: list[EnvPart] = []
        for i, e in enumerate(cfg.environment):
            closed = build_contact and e.collide and e.frame == cfg.frames.world
            mesh = load_mesh(e.mesh, e.units, f"environment mesh {e.name!r}", closed=closed, notes=notes)
            _check_size(mesh, e.mesh, f"environment[{i}].units", e.units,
                        _MIN_OBJECT_EXTENT_M, _MAX_ENVIRONMENT_EXTENT_M, "a part of a work cell")
            self.parts.append(EnvPart(e, mesh, e.pose.matrix()))
            if e.occlude:
                self.renderer.add_mesh(f"env:{e.name}", mesh.vertices, mesh.faces)
        for note in notes:
            self.warnings.append(warning(None, "mesh_open" if "used as it is" in note else "mesh_repaired", note))
        self._check_object_scale()
        self.symmetries = np.stack([np.eye(4)] + [s.matrix() for s in cfg.object.symmetries])
        self.sdf: ObjectSignedDistance | None = None
        if build_contact:
            self._build_contact()

    def _check_object_scale(self) -> None:
        """Warn when the object's size does not fit the gripper-mounted meshes (fingers): a
        unit error the hard size limits cannot tell from a very large or small part."""
        cfg = self.cfg
        gripper = [(i, p) for i, p in enumerate(self.parts) if p.spec.frame != cfg.frames.world]
        if not gripper:
            return
        extent = float(np.max(self.object_mesh.extents))
        ref = float(np.median([np.max(p.mesh.extents) for _, p in gripper]))
        ratio = extent / ref
        if _MIN_OBJECT_TO_GRIPPER <= ratio <= _MAX_OBJECT_TO_GRIPPER:
            return
        keys = ", ".join(f"environment[{i}].units" for i, _ in gripper)
        self.warnings.append(warning(
            None, "units_suspect",
            f"{cfg.object.mesh}: the object is {extent:.4g} m across, {ratio:.3g} times the {ref:.3g} m of the "
            f"gripper-mounted meshes; check object.units ({cfg.object.units!r}) and {keys} (a mesh in millimetres "
            "declared as metres is 1000 times too large)",
            object_extent_m=extent, gripper_extent_m=ref, ratio=ratio,
        ))

    def _build_contact(self) -> None:
        """Signed-distance grid of the world-fixed environment meshes around the receptacle."""
        fixed = [p for p in self.parts if p.spec.collide and p.spec.frame == self.cfg.frames.world]
        if not fixed:
            return
        meshes = [p.mesh for p in fixed]
        poses = np.stack([p.T_frame_mesh for p in fixed])
        # Where the grid lies and how fine: contact/grid.py (a warning when coarser than the clearance)
        boxes = [trimesh.transformations.transform_points(trimesh.bounds.corners(m.bounds), T)
                 for m, T in zip(meshes, poses)]
        bounds, res, coarse = contact_grid(boxes, float(np.max(self.object_mesh.extents)),
                                           self.cfg.contact.sdf_resolution_m, self.cfg.object.clearance_m)
        if coarse is not None:
            self.warnings.append(warning(None, "contact_grid_coarse", coarse, resolution_m=res,
                                         clearance_m=self.cfg.object.clearance_m))
        self.sdf = ObjectSignedDistance.from_meshes(
            self.object_mesh, meshes, poses, bounds, rng=np.random.default_rng(0), resolution_m=res,
            n_points=1000, use_fcl=False, cache_dir=cache_dir(),
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


def _check_size(mesh: trimesh.Trimesh, path, key: str, units: str, lo_m: float, hi_m: float, what: str) -> None:
    """``MeshError`` naming the file and the units key when the mesh (already in metres) is
    larger or smaller than ``what`` can be: a unit error (1000x)."""
    extent = float(np.max(mesh.extents))
    if lo_m <= extent <= hi_m:
        return
    hint = "mm" if (extent > hi_m and units == "m") else "m" if (extent < lo_m and units == "mm") else None
    fix = (f"is it in {'millimetres' if hint == 'mm' else 'metres'} (set {key}: {hint!r})?" if hint
           else "check the mesh's scale")
    raise MeshError(
        f"{path}: mesh is {extent:g} m across with {key}: {units!r}, "
        f"but {what} is {1e3 * lo_m:g} mm to {hi_m:g} m; {fix}"
    )
