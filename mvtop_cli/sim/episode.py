"""The insertion episode: grasp offset, approach, descent until contact, slip under contact.

Only geometry decides contact: the object is lowered with the end effector until it would
penetrate the receptacle (python-fcl distance between the meshes), the end effector stops
there, and the contact flag is true while the object touches the receptacle. Under contact the
object may slip a little in the grasp; the slip is resolved against penetration too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from ..contact.fcl_distance import FclDistance
from ..errors import ConfigError
from ..geometry import se3
from .gripper import pad_band_extent

CONTACT_DISTANCE_M = 5e-5  # distance below which the object is reported touching [m]
_BISECTION_STEPS = 24  # halvings of the descent step: < 1e-7 m residual on a 1 mm step


@dataclass(frozen=True)
class EpisodeOptions:
    """Randomisation of one episode (SI units; rotations in degrees)."""

    frames: int = 30
    rate_hz: float = 10.0
    grasp_translation_m: float = 0.003  # half-width of the uniform in-hand offset along ee x and z
    grasp_rotation_deg: float = 10.0  # half-width of the in-plane rotation about the pad normal (ee y)
    grasp_tilt_deg: float = 2.0  # half-width of the tilt about ee x and ee z (pads flatten it)
    slip_translation_m: float = 1e-4  # std of slip per contact frame
    slip_rotation_deg: float = 0.2  # std of rotational slip per contact frame
    indentation_m: float = 6e-4  # gel indentation at the deepest point of each pad
    approach_height_m: float = 0.030  # start height of the object above the receptacle mouth
    hover_height_m: float = 0.004  # height at the end of the approach
    descent_step_m: float = 0.0015  # commanded descent per frame
    wiggle_m: float = 5e-4  # lateral search motion while in contact
    start_time_ns: int = 1_700_000_000_000_000_000


@dataclass
class EpisodeState:
    """One frame of ground truth: time, end effector, object in hand, finger pads, contact."""

    stamp_ns: int
    T_world_ee: np.ndarray
    T_ee_object: np.ndarray
    pad_left_y_m: float  # pad surface positions along ee y [m]
    pad_right_y_m: float
    contact: bool
    distance_m: float  # object-to-environment distance [m] (0 when touching)
    press_force_n: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def T_world_object(self) -> np.ndarray:
        return self.T_world_ee @ self.T_ee_object

    @property
    def finger_opening_m(self) -> float:
        return self.pad_left_y_m - self.pad_right_y_m


class Collider:
    """Distance [m] between the object and fixed environment meshes (world frame).

    python-fcl returns the exact distance for separated meshes and 0 for touching or
    penetrating ones, which is all the episode needs: it only ever moves to poses with
    distance > 0.
    """

    def __init__(self, object_mesh: trimesh.Trimesh, environment: list[tuple[trimesh.Trimesh, np.ndarray]]):
        self._fcl = FclDistance(object_mesh, [m for m, _ in environment], np.stack([T for _, T in environment]))

    def distance(self, T_world_object: np.ndarray) -> float:
        """Smallest distance [m] from the object at ``T_world_object`` to the environment."""
        return float(max(0.0, self._fcl.distance(T_world_object)))


def sample_grasp_offset(options: EpisodeOptions, rng: np.random.Generator) -> np.ndarray:
    """In-hand offset: a rotation (about the object's origin) and translation, both in ee
    axes; apply with :func:`apply_offset`."""
    tx, tz = rng.uniform(-options.grasp_translation_m, options.grasp_translation_m, size=2)
    ry = rng.uniform(-options.grasp_rotation_deg, options.grasp_rotation_deg)
    rx, rz = rng.uniform(-options.grasp_tilt_deg, options.grasp_tilt_deg, size=2)
    R = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()
    return se3.make_pose(R, [tx, 0.0, tz])


def apply_offset(offset: np.ndarray, T_ee_object: np.ndarray) -> np.ndarray:
    """``T_ee_object`` rotated by ``offset``'s rotation about the object's own origin and moved
    by its translation, both expressed in ee axes (the convention of the grasp prior)."""
    return se3.make_pose(offset[:3, :3] @ T_ee_object[:3, :3], T_ee_object[:3, 3] + offset[:3, 3])


def centre_between_pads(
    T_ee_object: np.ndarray, mesh: trimesh.Trimesh, indentation_m: float, squeeze: str = "pads"
) -> tuple[np.ndarray, float, float]:
    """Shift the object along ee y so the two pads squeeze it symmetrically, and place the pads
    ``indentation_m`` inside its extent along ee y: with ``squeeze`` ``pads`` the extent of its
    surface within the pads' band (``gripper.pad_band_extent``), with ``widest`` that of all its
    vertices. Returns (T_ee_object, pad_left_y, pad_right_y) [m]."""
    if squeeze == "widest":
        y = se3.transform_points(T_ee_object, mesh.vertices)[:, 1]
        lo, hi = y.min(), y.max()
    elif squeeze == "pads":
        extent = pad_band_extent(mesh.vertices, mesh.edges_unique, T_ee_object)
        if extent is None:
            raise ConfigError("the gripper's pads do not reach the part at the sampled grasp offset: grasp.height_m "
                              "is too close to the part's end for the in-hand offset (EpisodeOptions)")
        lo, hi = extent
    else:
        raise ValueError(f"squeeze must be 'pads' or 'widest', got {squeeze!r}")
    shift = -(hi + lo) / 2.0
    T = T_ee_object.copy()
    T[1, 3] += shift
    half = (hi - lo) / 2.0
    return T, half - indentation_m, -(half - indentation_m)


def plan_episode(
    T_world_receptacle: np.ndarray,
    insertion_depth_m: float,
    T_ee_object_nominal: np.ndarray,
    object_mesh: trimesh.Trimesh,
    collider: Collider,
    options: EpisodeOptions,
    rng: np.random.Generator,
    squeeze: str = "pads",
) -> list[EpisodeState]:
    """Ground-truth states of every frame of one episode; ``squeeze`` where the pads close on
    the part (``centre_between_pads``)."""
    offset = sample_grasp_offset(options, rng)
    T_ee_obj, pad_l, pad_r = centre_between_pads(
        apply_offset(offset, T_ee_object_nominal), object_mesh, options.indentation_m, squeeze
    )

    # Commanded end-effector poses assume the nominal grasp: the object is believed to sit at
    # T_ee_object_nominal, so the robot aims that belief at the receptacle.
    yaw = Rotation.from_euler("z", rng.uniform(-25.0, 25.0), degrees=True).as_matrix()
    T_world_target_obj = T_world_receptacle @ se3.make_pose(yaw, [0.0, 0.0, -insertion_depth_m])
    T_world_ee_inserted = T_world_target_obj @ se3.invert(T_ee_object_nominal)

    def ee_at_height(h: float, lateral: np.ndarray) -> np.ndarray:
        T = T_world_ee_inserted.copy()
        T[:3, 3] += np.array([lateral[0], lateral[1], h + insertion_depth_m])
        return T

    n = options.frames
    n_approach = max(2, int(round(0.45 * n)))
    start_lateral = rng.uniform(-0.02, 0.02, size=2)
    swing = se3.make_pose(Rotation.from_euler("z", rng.uniform(-15, 15), degrees=True).as_matrix(), np.zeros(3))
    T_start = ee_at_height(options.approach_height_m, start_lateral)
    T_start[:3, :3] = swing[:3, :3] @ T_start[:3, :3]
    T_hover = ee_at_height(options.hover_height_m, np.zeros(2))

    states: list[EpisodeState] = []
    dt_ns = int(round(1e9 / options.rate_hz))
    T_ee_cmd = T_start
    in_contact_frames = 0
    for k in range(n):
        stamp = options.start_time_ns + k * dt_ns
        if k < n_approach:
            a = k / (n_approach - 1)
            a = 0.5 - 0.5 * np.cos(np.pi * a)  # smooth start and stop
            T_ee = se3.interpolate(T_start, T_hover, a)
            d = collider.distance(T_ee @ T_ee_obj)
            states.append(EpisodeState(stamp, T_ee, T_ee_obj.copy(), pad_l, pad_r, d < CONTACT_DISTANCE_M, d))
            T_ee_cmd = T_ee
            continue

        prev_ok = T_ee_cmd
        target = T_ee_cmd.copy()
        target[2, 3] -= options.descent_step_m
        if in_contact_frames > 0 and options.wiggle_m > 0:
            target[:2, 3] += rng.normal(0.0, options.wiggle_m / 2.0, size=2)
            prev_ok = prev_ok.copy()
            prev_ok[:2, 3] = target[:2, 3]
        if in_contact_frames > 0:
            slip = se3.make_pose(
                Rotation.from_rotvec(np.radians(rng.normal(0.0, options.slip_rotation_deg, 3))).as_matrix(),
                rng.normal(0.0, options.slip_translation_m, 3),
            )
            T_ee_obj, pad_l, pad_r = centre_between_pads(
                apply_offset(slip, T_ee_obj), object_mesh, options.indentation_m, squeeze
            )
        prev_ok = _lift_until_free(prev_ok, T_ee_obj, collider)
        T_ee, d = _descend_until_contact(prev_ok, target, T_ee_obj, collider)
        contact = d < CONTACT_DISTANCE_M
        in_contact_frames = in_contact_frames + 1 if contact else 0
        force = 5.0 + rng.normal(0.0, 0.3) if contact else rng.normal(0.0, 0.05)
        states.append(EpisodeState(stamp, T_ee, T_ee_obj.copy(), pad_l, pad_r, contact, d, force))
        T_ee_cmd = T_ee
    return states


def _lift_until_free(T_ee: np.ndarray, T_ee_obj: np.ndarray, collider: Collider) -> np.ndarray:
    """Raise the end effector in 1 mm steps until the object is clear of the environment."""
    T = T_ee.copy()
    for _ in range(100):
        if collider.distance(T @ T_ee_obj) > 0.0:
            return T
        T[2, 3] += 0.001
    raise RuntimeError("simulated object stays in collision 0.1 m above its contact pose")


def _descend_until_contact(
    T_free: np.ndarray, T_target: np.ndarray, T_ee_obj: np.ndarray, collider: Collider
) -> tuple[np.ndarray, float]:
    """Move from the free pose ``T_free`` towards ``T_target`` (same orientation) and stop at the
    first contact: the last collision-free pose along the segment, found by bisection."""
    d = collider.distance(T_target @ T_ee_obj)
    if d > 0.0:
        return T_target, d
    lo, hi = 0.0, 1.0  # fraction of the way; lo is free, hi collides
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        T = T_free.copy()
        T[:3, 3] = (1 - mid) * T_free[:3, 3] + mid * T_target[:3, 3]
        if collider.distance(T @ T_ee_obj) > 0.0:
            lo = mid
        else:
            hi = mid
    T = T_free.copy()
    T[:3, 3] = (1 - lo) * T_free[:3, 3] + lo * T_target[:3, 3]
    return T, collider.distance(T @ T_ee_obj)


def state_at(states: list[EpisodeState], t_ns: int) -> EpisodeState:
    """The episode at time ``t_ns`` between its frames: end effector and object each
    interpolated in world (linear translation, slerp rotation, as a TF or ground-truth
    reader interpolates them), pad positions linearly; contact, distance and force those of
    the frame at or before ``t_ns``. Before the first frame or after the last, that frame."""
    stamps = np.array([s.stamp_ns for s in states], dtype=np.int64)
    i = int(np.searchsorted(stamps, t_ns, side="right")) - 1
    if i < 0:
        return states[0]
    if i >= len(states) - 1 or t_ns == stamps[i]:
        return states[i]
    a, b = states[i], states[i + 1]
    alpha = (t_ns - int(stamps[i])) / (int(stamps[i + 1]) - int(stamps[i]))
    T_world_ee = se3.interpolate(a.T_world_ee, b.T_world_ee, alpha)
    T_world_obj = se3.interpolate(a.T_world_object, b.T_world_object, alpha)

    def lerp(x: float, y: float) -> float:
        return (1.0 - alpha) * x + alpha * y

    return EpisodeState(
        int(t_ns), T_world_ee, se3.invert(T_world_ee) @ T_world_obj, lerp(a.pad_left_y_m, b.pad_left_y_m),
        lerp(a.pad_right_y_m, b.pad_right_y_m), a.contact, a.distance_m, a.press_force_n,
    )
