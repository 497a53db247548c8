"""Exact object-to-environment distance for separated poses with python-fcl (BVH vs BVH)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvtop_cli.errors import MeshError


def _import_fcl():
    """python-fcl, imported on first use so that grid-only users do not need it."""
    try:
        import fcl
    except ImportError as err:  # pragma: no cover - python-fcl is a declared dependency
        raise ImportError("FclDistance needs python-fcl: pip install python-fcl") from err
    return fcl


def _bvh_model(fcl, vertices: np.ndarray, faces: np.ndarray, name: str):
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise MeshError(f"{name}: expected (n, 3) vertices, got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise MeshError(f"{name}: expected (m, 3) triangle faces, got shape {faces.shape}")
    model = fcl.BVHModel()
    model.beginModel(len(vertices), len(faces))
    model.addSubModel(vertices, faces)
    model.endModel()
    return model


def _fcl_transform(fcl, T: np.ndarray):
    return fcl.Transform(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]))


class FclDistance:
    """Minimum distance [m] between an object mesh at given poses and static environment meshes.

    Both sides are FCL BVH models (triangle soups), so the result is the distance between the
    two *surfaces*: exact (to float precision) when the solids are separated, and 0 when any
    triangles intersect. FCL reports neither a penetration depth for mesh pairs (it returns 0)
    nor anything meaningful when one solid lies entirely inside the other without the surfaces
    crossing (the surface gap is returned); use :class:`~mvtop_cli.contact.sdf.EnvironmentSDF`
    for signed values. Cost: about 0.1-4 ms per pose for the IndustReal 12 mm peg (1424
    triangles) against its socket (21854 triangles), most when the peg is deep in the hole.

    Parameters
    ----------
    object_mesh : trimesh.Trimesh
        The object in its own frame [m].
    env_meshes : sequence of trimesh.Trimesh
        Environment meshes (receptacle, table, ...) each in its own frame [m].
    T_world_env : (M, 4, 4) float, optional
        Pose of each environment mesh in the world frame; identity when omitted.
    """

    def __init__(self, object_mesh, env_meshes: Sequence, T_world_env: np.ndarray | None = None):
        fcl = _import_fcl()
        self._fcl = fcl
        env_meshes = list(env_meshes)
        if not env_meshes:
            raise MeshError("FclDistance: no environment meshes given")
        if T_world_env is None:
            T_world_env = np.tile(np.eye(4), (len(env_meshes), 1, 1))
        T_world_env = np.asarray(T_world_env, dtype=np.float64).reshape(-1, 4, 4)
        if len(T_world_env) != len(env_meshes):
            raise ValueError(
                f"{len(env_meshes)} environment meshes but {len(T_world_env)} poses in T_world_env"
            )
        self._object = fcl.CollisionObject(
            _bvh_model(fcl, object_mesh.vertices, object_mesh.faces, "object mesh"),
            fcl.Transform(),
        )
        self._env = [
            fcl.CollisionObject(
                _bvh_model(fcl, m.vertices, m.faces, f"environment mesh {i}"),
                _fcl_transform(fcl, T),
            )
            for i, (m, T) in enumerate(zip(env_meshes, T_world_env))
        ]
        self._request = fcl.DistanceRequest()

    def distance(self, T_world_object: np.ndarray) -> np.ndarray:
        """Surface distance [m] for poses ``T_world_object`` (N, 4, 4) -> (N,), or (4, 4) -> ().

        Exact when separated; 0 when the surfaces touch or intersect (never negative).
        """
        T = np.asarray(T_world_object, dtype=np.float64)
        single = T.ndim == 2
        T = T.reshape(-1, 4, 4)
        out = np.empty(len(T))
        for n, T_n in enumerate(T):
            self._object.setTransform(_fcl_transform(self._fcl, T_n))
            d = np.inf
            for env in self._env:
                result = self._fcl.DistanceResult()
                d = min(d, self._fcl.distance(self._object, env, self._request, result))
            # FCL reports -1 for some geometry pairs in collision; only "touching or worse"
            # is known then, which is 0 here.
            out[n] = max(d, 0.0)
        return out[0] if single else out
