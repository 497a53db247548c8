"""Throughput of particle scoring (render + IoU) for 2 cameras and 2 tactile sensors, batched vs per-pose pyrender."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import trimesh
from numba import get_num_threads

from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.render.iou import iou_scores
from mvtop_cli.render.numba_renderer import NumbaMaskRenderer
from mvtop_cli.render.roi import Roi, roi_for_particles

GEL_DISTANCE_M = 0.025
PRESS_DEPTH_M = 0.0005  # how far the true pose presses into each gel


@dataclass(frozen=True)
class _Sensor:
    name: str
    camera: PinholeCamera
    T_sensor_object: np.ndarray  # (4, 4) at the true pose
    tactile: bool


def _look_at(position: np.ndarray, target: np.ndarray = np.zeros(3)) -> np.ndarray:
    """T_object_camera of an optical frame at ``position`` looking at ``target`` (z up = image up)."""
    z = target - position
    z /= np.linalg.norm(z)
    y = np.array([0.0, 0.0, -1.0]) - z * -z[2]
    y /= np.linalg.norm(y)
    return se3.make_pose(np.column_stack([np.cross(y, z), y, z]), position)


def default_meshes() -> dict[str, trimesh.Trimesh]:
    """The benchmark's objects: a 25 mm cube and an 8 x 5 x 12 mm connector-sized box."""
    return {
        "cube_25mm": trimesh.creation.box((0.025, 0.025, 0.025)),
        "connector_8x5x12mm": trimesh.creation.box((0.008, 0.005, 0.012)),
    }


def _sensors(mesh: trimesh.Trimesh) -> list[_Sensor]:
    """Two cameras 0.35-0.5 m away and two tactile sensors pressing the object's +-y faces."""
    cam = PinholeCamera(640, 480, np.array([[615.0, 0.0, 319.5], [0.0, 615.0, 239.5], [0.0, 0.0, 1.0]]))
    tac = PinholeCamera(320, 240, np.array([[416.0, 0.0, 159.5], [0.0, 416.0, 119.5], [0.0, 0.0, 1.0]]))
    out = []
    for name, pos in (("camera_front", [0.30, -0.20, 0.22]), ("camera_side", [-0.25, -0.35, 0.18])):
        out.append(_Sensor(name, cam, se3.invert(_look_at(np.asarray(pos))), False))
    lo, hi = mesh.bounds
    centre_x, centre_z = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    for name, side in (("tactile_left", 1.0), ("tactile_right", -1.0)):
        face_y = hi[1] if side > 0 else lo[1]
        # Optical z points at the object (along -side * y); image x along object x.
        z = np.array([0.0, -side, 0.0])
        x = np.array([1.0, 0.0, 0.0])
        R = np.column_stack([x, np.cross(z, x), z])
        pos = np.array([centre_x, face_y + side * (GEL_DISTANCE_M - PRESS_DEPTH_M), centre_z])
        out.append(_Sensor(name, tac, se3.invert(se3.make_pose(R, pos)), True))
    return out


def _particles(rng: np.random.Generator, n: int, sigma_m: float, sigma_rad: float) -> np.ndarray:
    """(n, 4, 4) T_true_particle: perturbations of the true pose."""
    return se3.make_pose(
        se3.rotvec_to_matrix(rng.normal(scale=sigma_rad, size=(n, 3))), rng.normal(scale=sigma_m, size=(n, 3))
    )


def benchmark_render(
    particles_list: Sequence[int] = (250, 1000, 4000),
    meshes: Mapping[str, trimesh.Trimesh] | None = None,
    reference: bool = True,
    reference_max_particles: int = 64,
    repeats: int = 7,
    max_side: int = 128,
    sigma_m: float = 0.002,
    sigma_rad: float = 0.05,
    seed: int = 0,
) -> list[dict]:
    """Particle x sensor evaluations per second (render + IoU, ROI and observed-mask crop
    included) for each particle count and mesh, over 2 cameras and 2 tactile sensors.

    The batched path is :meth:`NumbaMaskRenderer.score_masks` (best of ``repeats``); the
    reference path renders each particle with one pyrender render (``PyrenderMaskRenderer``)
    and scores the masks with :func:`iou_scores`, timed on at most
    ``reference_max_particles`` particles per sensor (its rate does not depend on N).
    Particles scatter around the true pose by ``sigma_m`` [m] and ``sigma_rad`` [rad].
    Returns one dict per (mesh, particle count): mesh, particles, sensors, roi_shapes,
    evals_per_s, seconds, reference_evals_per_s (None without ``reference``), threads.
    """
    meshes = dict(default_meshes() if meshes is None else meshes)
    rng = np.random.default_rng(seed)
    fast = NumbaMaskRenderer()
    ref = None
    if reference:
        from mvtop_cli.render.pyrender_renderer import PyrenderMaskRenderer

        ref = PyrenderMaskRenderer()
    results = []
    try:
        for mesh_id, mesh in meshes.items():
            fast.add_mesh(mesh_id, mesh.vertices, mesh.faces)
            if ref is not None:
                ref.add_mesh(mesh_id, mesh.vertices, mesh.faces)
            sensors = _sensors(mesh)
            observed = {}
            for s in sensors:
                mode = dict(mode="tactile", gel_distance_m=GEL_DISTANCE_M) if s.tactile else {}
                full = Roi.full(s.camera)
                observed[s.name] = fast.render_masks(mesh_id, s.T_sensor_object, s.camera, full, **mode)[0]

            def score_all(
                T_true_particles: np.ndarray, renderer, per_pose: bool,
                sensors=sensors, mesh_id=mesh_id, observed=observed,
            ) -> list[tuple[int, int]]:
                shapes = []
                for s in sensors:
                    mode = dict(mode="tactile", gel_distance_m=GEL_DISTANCE_M) if s.tactile else {}
                    T = s.T_sensor_object @ T_true_particles
                    roi = roi_for_particles(fast.mesh(mesh_id), T, s.camera, max_side=max_side, **mode)
                    obs = roi.crop(observed[s.name])
                    outside = roi.outside_area(observed[s.name])
                    if per_pose:  # the reference renders pose by pose, then scores
                        iou_scores(renderer.render_masks(mesh_id, T, s.camera, roi, **mode), obs, outside)
                    else:
                        renderer.score_masks(mesh_id, T, s.camera, roi, obs, observed_outside=outside, **mode)
                    shapes.append(roi.shape)
                return shapes

            score_all(_particles(rng, 8, sigma_m, sigma_rad), fast, False)  # compile / load kernels
            for n in particles_list:
                T_particles = _particles(rng, n, sigma_m, sigma_rad)
                times = []
                for _ in range(max(1, repeats)):
                    t0 = time.perf_counter()
                    shapes = score_all(T_particles, fast, False)
                    times.append(time.perf_counter() - t0)
                best = min(times)
                ref_rate = None
                if ref is not None:
                    n_ref = min(n, reference_max_particles)
                    score_all(T_particles[:2], ref, True)  # create the GL context, upload meshes
                    t0 = time.perf_counter()
                    score_all(T_particles[:n_ref], ref, True)
                    ref_rate = n_ref * len(sensors) / (time.perf_counter() - t0)
                results.append(
                    dict(
                        mesh=mesh_id,
                        particles=int(n),
                        sensors=len(sensors),
                        roi_shapes=shapes,
                        seconds=best,
                        evals_per_s=n * len(sensors) / best,
                        reference_evals_per_s=ref_rate,
                        threads=get_num_threads(),
                    )
                )
    finally:
        if ref is not None:
            ref.close()
    return results
