"""CHSEL registers labelled points to the object (runs only where the baseline extra is installed)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from mvtop_cli.benchmarks.baselines.points import FREE, SURFACE, LabelledPoints
from mvtop_cli.geometry import se3

chsel_runner = pytest.importorskip("mvtop_cli.benchmarks.baselines.chsel_runner")
if not chsel_runner.available():
    pytest.skip("the CHSEL baseline extra (torch, chsel) is not installed", allow_module_level=True)


def test_chsel_recovers_a_box_from_surface_and_free_points():
    rng = np.random.default_rng(0)
    box = trimesh.creation.box(extents=(0.02, 0.012, 0.008))
    T_true = se3.exp_se3(np.array([0.004, -0.002, 0.03, 0.3, -0.2, 0.5]))
    # surface: the two large faces (as two tactile pads would see them) and one end face
    s, idx = trimesh.sample.sample_surface_even(box, 3000, seed=1)
    normals = box.face_normals[idx]
    keep = (np.abs(normals[:, 2]) > 0.9) | (normals[:, 0] > 0.9)
    surface = s[keep]
    # free space: a shell 1-4 mm outside the box all around (as carved by cameras)
    shell = rng.uniform(-0.014, 0.014, (40000, 3))
    d = trimesh.proximity.signed_distance(box, shell)  # positive inside
    free = shell[(d < -1e-3) & (d > -4e-3)]
    pts = LabelledPoints.concat([LabelledPoints.of(se3.transform_points(T_true, surface), SURFACE),
                                 LabelledPoints.of(se3.transform_points(T_true, free), FREE)])
    # initial poses: a +-2 mm, +-8 deg prior around the truth
    init = np.stack([T_true @ se3.exp_se3(np.concatenate([rng.uniform(-2e-3, 2e-3, 3), rng.uniform(-0.14, 0.14, 3)]))
                     for _ in range(16)])
    options = chsel_runner.ChselOptions(resolution_m=1e-3, qd_iterations=30, threads=1)
    reg = chsel_runner.register(pts, box.vertices, box.faces, init, seed=0, options=options)
    dt = np.linalg.norm(reg.T_ref_object[:3, 3] - T_true[:3, 3])
    dr = np.degrees(se3.rotation_angle(reg.T_ref_object[:3, :3], T_true[:3, :3]))
    start = [np.linalg.norm(T[:3, 3] - T_true[:3, 3]) for T in init]
    # the box's 180 deg symmetries are excluded by the one-sided end face's surface points
    assert dt < 0.5e-3 and dr < 3.0, (dt, dr)
    assert dt < np.median(start)
    assert reg.costs.shape == (16,) and reg.solutions.shape == (16, 4, 4)
    assert np.all(np.linalg.eigvalsh(reg.covariance) > 0)
    again = chsel_runner.register(pts, box.vertices, box.faces, init, seed=0, options=options)
    np.testing.assert_allclose(again.T_ref_object, reg.T_ref_object, atol=1e-6)  # seeded: the same result


def test_no_surface_points_is_one_clear_error():
    box = trimesh.creation.box(extents=(0.02, 0.012, 0.008))
    pts = LabelledPoints.of(np.zeros((5, 3)), FREE)
    with pytest.raises(chsel_runner.MvtopError, match="at least one surface point"):
        chsel_runner.register(pts, box.vertices, box.faces, np.eye(4)[None], seed=0)


def test_no_tbb_warning_when_the_baseline_loads_its_libtbb_first():
    """open3d (pulled in by the baseline) bundles a libtbb older than numba supports; loaded
    before the first parallel kernel, numba used to warn about it on stderr in every
    benchmark run with CHSEL."""
    import subprocess
    import sys

    code = (
        "import open3d\n"
        "import numpy as np\n"
        "from mvtop_cli.render.numba_renderer import NumbaMaskRenderer\n"
        "import trimesh\n"
        "from mvtop_cli.geometry.camera import PinholeCamera\n"
        "from mvtop_cli.render.roi import Roi\n"
        "r = NumbaMaskRenderer()\n"
        "box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))\n"
        "r.add_mesh('box', box.vertices, box.faces)\n"
        "cam = PinholeCamera(64, 48, np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]))\n"
        "T = np.eye(4); T[2, 3] = 0.2\n"
        "print(int(r.render_masks('box', T[None], cam, Roi.full(cam), [])[0].sum()))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout) > 0
    assert "TBB" not in proc.stderr, proc.stderr
