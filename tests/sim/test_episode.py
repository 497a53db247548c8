"""Where the simulated pads close on the part (sim/episode.centre_between_pads)."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.errors import ConfigError
from mvtop_cli.geometry import se3
from mvtop_cli.sim.episode import centre_between_pads
from mvtop_cli.sim.gripper import pad_band_extent
from mvtop_cli.sim.objects import get_object, list_objects


def blades_grasp(offset_y_m: float = 0.0) -> np.ndarray:
    """The plug held at 6 mm above its blade tips: the pads' band holds only the 6.35 mm blades,
    the 22 mm body starts above it; the part shifted ``offset_y_m`` along ee y."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (0.0, offset_y_m, 0.006)
    return T


def test_pads_close_on_the_band_not_on_the_widest_extent():
    plug = get_object("plug")  # blades 1.52 x 6.35 mm below a 30 x 22 mm body
    T, left, right = centre_between_pads(blades_grasp(0.0013), plug.mesh, 6e-4, "pads")
    assert left - right == pytest.approx(0.00635 - 2 * 6e-4, abs=1e-9)
    lo, hi = pad_band_extent(plug.mesh.vertices, plug.mesh.edges_unique, T)
    assert (lo + hi) / 2 == pytest.approx(0.0, abs=1e-12)  # the blades centred between the pads
    _, left_w, right_w = centre_between_pads(blades_grasp(0.0013), plug.mesh, 6e-4, "widest")
    assert left_w - right_w == pytest.approx(0.022 - 2 * 6e-4, abs=1e-9)


@pytest.mark.parametrize("name", list_objects())
def test_builtin_objects_keep_the_widest_extent_their_sample_logs_were_made_with(name):
    spec = get_object(name)
    assert spec.grasp_squeeze == "widest"
    T = se3.make_pose(se3.rotvec_to_matrix(np.radians([2.0, 8.0, -2.0])), [0.002, 0.0, -0.001]) @ spec.grasp
    out, left, right = centre_between_pads(T, spec.mesh, 6e-4, "widest")
    y = se3.transform_points(out, spec.mesh.vertices)[:, 1]
    assert (y.max() + y.min()) / 2 == pytest.approx(0.0, abs=1e-12)
    assert left - right == pytest.approx(y.max() - y.min() - 1.2e-3, abs=1e-12)


def test_a_part_out_of_the_pads_band_is_a_config_error():
    plug = get_object("plug")
    T = blades_grasp()
    T[2, 3] = -0.02  # the part entirely beyond the fingertips
    with pytest.raises(ConfigError, match="pads do not reach the part"):
        centre_between_pads(T, plug.mesh, 6e-4, "pads")
