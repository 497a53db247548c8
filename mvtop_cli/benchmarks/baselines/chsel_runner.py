"""CHSEL registration (Zhong et al., "CHSEL: Producing diverse plausible pose estimates from
contact and free space data", RSS 2023) of labelled points against the object's mesh.

torch, chsel and its volumetric helpers are imported when a registration runs: they are the
optional ``baseline`` extra, and a missing install stops with the one pip command to run.
Known traps of chsel 0.2.1 with pytorch_volumetric 0.6.0 / pytorch_kinematics 0.10.0 avoided
here: points go in as ``positions`` + ``semantics`` (``surface_pts`` / ``free_pts`` fail),
the model's query grid is given tight (the default pads the object by 10 cm, ~10^8 voxels at
0.5 mm), the cached SDF uses nearest lookup (linear fails on float32 points), and the initial
poses come from the grasp prior rather than chsel's own re-initialisation (which calls a
function pytorch_kinematics 0.10 no longer exports).
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from ...errors import MvtopError
from ...geometry import se3
from .points import FREE, SURFACE, LabelledPoints

INSTALL_HINT = "pip install -e '.[baseline]' in the mvtop checkout (or: pip install torch==2.13.0 chsel==0.2.1)"
_QUERY_PADDING_M = 1.5e-3  # the model's query grid: bounding box plus this on every side
_SDF_PADDING_M = 1e-2  # the cached SDF grid: bounding box plus this (beyond: distance to the box)
COST_RATIO = 2.0  # solutions within this factor of the best cost make the reported spread
_COVARIANCE_FLOOR = np.array([1e-12] * 3 + [1e-12] * 3)  # (1 um)^2, (1 urad)^2
# chsel's gradient descent takes Adam steps of 0.01 (its learning rate, not exposed) in the
# units of the points, and its quality-diversity archive has a minimum bin size of 2e-4: tuned
# for objects of 10-30 cm in metres. Parts of 1-5 cm in metres would move 10 mm a step, so
# points and mesh are handed over in centimetres (a step of 0.1 mm); results are converted back.
UNITS_PER_M = 100.0
_INTERIOR_VOXELS = 16000  # default resolution: about this many voxels inside the object
_MIN_RESOLUTION_M = 5e-4


class BaselineUnavailable(MvtopError):
    """The optional baseline dependencies are not installed."""


def require():
    """torch, chsel and pytorch_volumetric, imported; BaselineUnavailable (one line saying what
    to install) when they cannot be."""
    try:
        import chsel  # noqa: F401
        import pytorch_volumetric  # noqa: F401
        import torch  # noqa: F401
    except (ImportError, OSError) as err:
        if "libusb" in str(err):  # open3d, imported by chsel's helpers, without its system library
            raise BaselineUnavailable(
                "the CHSEL baseline cannot load libusb-1.0 for open3d; "
                "on Debian/Ubuntu: apt-get install -y libusb-1.0-0"
            ) from None
        what = getattr(err, "name", None) or str(err).splitlines()[0]
        raise BaselineUnavailable(
            f"the CHSEL baseline needs torch and chsel ({what} is missing): {INSTALL_HINT}"
        ) from None
    import chsel
    import pytorch_volumetric as pv
    import torch

    return chsel, pv, torch


def available() -> bool:
    """Whether torch and chsel can be imported here."""
    try:
        require()
    except BaselineUnavailable:
        return False
    return True


@dataclass(frozen=True)
class ChselOptions:
    """Registration parameters.

    resolution_m : voxel side of the object model's interior points and of the free-space
        voxels [m] (CHSEL's ``resolution``; a model point counts as interior, and a free
        voxel as violated, only this deep inside the object); None: the side that puts about
        16 000 voxels inside the object (the cost's size per pose), at least 0.5 mm
    batch : poses optimised together (initial poses drawn from the grasp prior)
    iterations : CHSEL iterations (each: gradient descent, then quality-diversity search
        re-initialised around the elites)
    qd_iterations : quality-diversity iterations per CHSEL iteration
    threads : torch threads (None: torch's default)
    """

    resolution_m: float | None = None
    batch: int = 30
    iterations: int = 1
    qd_iterations: int = 100
    threads: int | None = None


@dataclass(frozen=True)
class Registration:
    """The registered object pose ``T_ref_object`` (4, 4) in the points' frame, the CHSEL cost
    of each returned solution (B,) with their poses (B, 4, 4), the spread of the near-best
    solutions as a 6x6 covariance (translation [m], rotation [rad], axes of the points'
    frame, about the best pose), and the time spent [s]: wall clock and the process's CPU
    time (all threads; on a shared machine the CPU time is the comparable figure)."""

    T_ref_object: np.ndarray
    costs: np.ndarray
    solutions: np.ndarray
    covariance: np.ndarray
    seconds: float
    cpu_seconds: float


def _o3d_mesh(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64))
    m.triangles = o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32))
    return m


def _spread(T_best: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Covariance (6, 6) of poses (K, 4, 4) about ``T_best``: translation offsets and rotation
    vectors of ``R_k R_best^T`` (axes of the reference frame)."""
    dt = T[:, :3, 3] - T_best[:3, 3]
    dw = se3.matrix_to_rotvec(T[:, :3, :3] @ T_best[:3, :3].T)
    e = np.concatenate([dt, dw], axis=1)
    return e.T @ e / len(e) + np.diag(_COVARIANCE_FLOOR)


def _sync_numba_threads() -> None:
    """chsel's quality-diversity search compiles numba kernels (ribs) on first use, and numba
    re-reads ``NUMBA_NUM_THREADS`` from the environment when it compiles: a value differing
    from the thread pool already launched by mvtop's kernels (e.g. unset, meaning all cores,
    in a benchmark worker launched with fewer) is a RuntimeError. Align the two."""
    import numba

    os.environ["NUMBA_NUM_THREADS"] = str(numba.config.NUMBA_NUM_THREADS)


def default_resolution_m(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Voxel side [m] putting about ``_INTERIOR_VOXELS`` voxels inside a closed mesh (its
    bounding box's volume for an open one), at least ``_MIN_RESOLUTION_M``."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
    volume = abs(float(mesh.volume)) if mesh.is_watertight else float(np.prod(mesh.extents))
    return max(_MIN_RESOLUTION_M, (volume / _INTERIOR_VOXELS) ** (1 / 3))


def register(
    points: LabelledPoints,
    vertices: np.ndarray,
    faces: np.ndarray,
    T_ref_object_init: np.ndarray,
    seed: int,
    options: ChselOptions = ChselOptions(),
) -> Registration:
    """Register ``points`` (any reference frame, e.g. the end effector's) to the object mesh
    ``vertices`` (V, 3) [m, object frame], ``faces`` (F, 3).

    T_ref_object_init : (B, 4, 4) initial object poses in the reference frame (e.g. grasp
        prior samples); ``options.batch`` is ignored in their favour
    seed : seeds torch and the global numpy generator chsel and its helpers draw from (the
        numpy state is restored afterwards)
    """
    if len(points.surface) == 0:
        raise MvtopError("CHSEL needs at least one surface point (no tactile contact was observed)")
    chsel, pv, torch = require()
    _sync_numba_threads()
    t0, c0 = time.perf_counter(), time.process_time()
    V = np.asarray(vertices, dtype=np.float64)
    res_m = options.resolution_m or default_resolution_m(V, faces)
    # chsel marks a free voxel for any free point in it: one point per voxel says the same
    points = LabelledPoints.concat([LabelledPoints.of(points.surface, SURFACE),
                                    LabelledPoints.of(points.free, FREE).downsampled(res_m)])
    # everything handed to chsel is in its units (see UNITS_PER_M)
    u = UNITS_PER_M
    V = V * u
    res = res_m * u
    lo, hi = V.min(axis=0), V.max(axis=0)
    np_state = np.random.get_state()
    threads = torch.get_num_threads()
    try:
        np.random.seed(seed % 2**32)
        torch.manual_seed(seed)
        if options.threads:
            torch.set_num_threads(options.threads)
        with tempfile.TemporaryDirectory(prefix="mvtop-chsel-") as tmp:
            factory = pv.MeshObjectFactory(mesh=_o3d_mesh(V, faces))
            box = np.stack([lo - _SDF_PADDING_M * u, hi + _SDF_PADDING_M * u], axis=1)
            sdf = pv.CachedSDF("object", res / 2, box, pv.MeshSDF(factory), method="nearest",
                               cache_path=os.path.join(tmp, "sdf.pkl"))
            query = pv.VoxelGrid(res, np.stack([lo - _QUERY_PADDING_M * u, hi + _QUERY_PADDING_M * u], axis=1),
                                 dtype=torch.float32)
            positions = torch.tensor(points.points * u, dtype=torch.float32)
            semantics = torch.tensor(np.where(points.labels == FREE, chsel.SemanticsClass.FREE.value,
                                              chsel.SemanticsClass.SURFACE.value), dtype=torch.long)
            assert SURFACE == chsel.SemanticsClass.SURFACE.value and FREE == chsel.SemanticsClass.FREE.value
            registration = chsel.CHSEL(sdf, positions=positions, semantics=semantics, resolution=res,
                                       query_voxel_grid=query, qd_iterations=options.qd_iterations, savedir=tmp)
            # CHSEL optimises H = T_object_ref (reference points into the object frame)
            H0 = se3.invert(np.asarray(T_ref_object_init, dtype=np.float64))
            H0[:, :3, 3] *= u
            H0 = torch.tensor(H0, dtype=torch.float32)
            result, _ = registration.register(iterations=options.iterations, initial_tsf=H0, batch=len(H0))
            H = chsel.solution_to_world_to_link_matrix(result).detach().cpu().numpy().astype(np.float64)
            costs = result.rmse.detach().cpu().numpy().astype(np.float64).reshape(-1)
    finally:
        np.random.set_state(np_state)
        torch.set_num_threads(threads)
    # re-orthonormalise (float32) before inverting
    U, _, Vt = np.linalg.svd(H[:, :3, :3])
    H[:, :3, :3] = U @ Vt
    H[:, :3, 3] /= u
    T = se3.invert(H)
    best = int(np.argmin(costs))
    near = costs <= costs[best] * COST_RATIO + 1e-12
    return Registration(
        T[best], costs, T, _spread(T[best], T[near]), time.perf_counter() - t0, time.process_time() - c0
    )
