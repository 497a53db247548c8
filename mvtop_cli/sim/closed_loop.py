"""Closed-loop insertion: a controller that aligns the estimated in-hand pose with the
receptacle, descends, and after a stalled descent backs off and tries again (the paper's
Table I experiment; ``benchmarks/insertion.py`` runs it over many grasps).

One grasp (``run_insertion``): the part is grasped with a random in-hand offset, as in
``episode.plan_episode`` (``EpisodeOptions``: offset, slip, pad indentation, frame rate), and
carried from a random start ``approach_height_m`` above the receptacle to the hover height.
Every frame the estimator (pluggable: any ``PoseEstimator``) returns its estimate of
``T_ee_object`` and the controller aims the end effector so that the *estimated* object
pose, ``T_world_ee @ T_ee_object_est``, sits over the receptacle's inserted pose: the estimate,
not the truth, decides where the part goes. After ``align_frames`` frames at the hover height
(re-aligned every frame), the end effector descends ``descent_step_m`` a frame, straight down
with the alignment of the last hover frame, as a guarded move: until contact stops it, at most
``overtravel_m`` below where the estimate puts the insertion depth (the receptacle's floor, 0.5 mm
below the depth, stops a part that is in; the overtravel covers an estimate that is off along
the approach axis, which would otherwise end the descent in free air short of the depth).

Contact is rigid and geometric, as in ``mvtop simulate``: a motion stops at the first contact
(python-fcl distance, found by bisection along the motion), so the parts never penetrate;
under contact the part slips in the grasp (``EpisodeOptions.slip_*``). A descent *stalls*
when, in contact, the end effector got less than ``stall_fraction`` of its step further down.
The controller then judges from its estimate: if the estimated leading face is within
``compliance_m`` of the insertion depth it stops (it believes the part inserted); otherwise
the attempt failed: it backs off to the hover height over ``backoff_frames`` frames, still
estimating, re-aligns with the latest estimate and descends again, up to ``attempts``
attempts in all.

Success is judged on the ground truth: the part's leading face (the object frame's origin,
``docs/frames.md``) ends at most ``compliance_m`` above the insertion depth. Parts never
penetrate (the contact is rigid), so the compliance is the depth tolerance a compliant wrist
or a final press would make up: 0.2 mm by default, below every receptacle's 0.5 mm floor gap
(``objects.FLOOR_GAP_MM``), so a part resting on the floor passes and one stopped on the rim
by a lateral error (the clearances are 0.25-0.3 mm a side) fails.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from ..geometry import se3
from ..records import Frame
from .episode import (
    CONTACT_DISTANCE_M,
    Collider,
    EpisodeOptions,
    EpisodeState,
    apply_offset,
    centre_between_pads,
    sample_grasp_offset,
)

_BISECTION_STEPS = 24  # halvings of a motion: < 1e-7 m residual on a 1.5 mm step
_LIFT_STEP_M = 1e-4  # a slip that would penetrate lifts the end effector in these steps [m] ...
_LIFT_MAX_STEPS = 30  # ... up to 3 mm, else the slip is not taken
OUTCOMES = ("inserted", "stalled", "believed_inserted")


@dataclass(frozen=True)
class ControllerOptions:
    """The insertion controller (SI units)."""

    attempts: int = 3  # descents before giving up
    approach_frames: int = 8  # frames from the start pose to the hover pose
    align_frames: int = 2  # frames at the hover height, re-aligned each, before a descent
    backoff_frames: int = 3  # frames from a stalled pose back up to the hover height
    approach_height_m: float = 0.030  # start height of the object above the receptacle mouth
    start_lateral_m: float = 0.02  # half-width of the uniform horizontal start offset
    start_yaw_deg: float = 15.0  # half-width of the uniform start yaw about world z
    hover_height_m: float = 0.004  # leading face above the mouth while aligning
    descent_step_m: float = 0.0015  # commanded descent per frame
    overtravel_m: float = 0.005  # the guarded descent's limit below the estimated insertion depth
    stall_fraction: float = 0.2  # in contact, less than this fraction of a step made: stalled
    compliance_m: float = 0.0002  # depth tolerance of success (the module docstring)

    def __post_init__(self) -> None:
        if self.attempts < 1 or self.approach_frames < 2 or self.align_frames < 1 or self.backoff_frames < 1:
            raise ValueError("attempts, align_frames and backoff_frames must be >= 1 and approach_frames >= 2")
        if self.descent_step_m <= 0 or self.compliance_m < 0 or self.overtravel_m < 0:
            raise ValueError("descent_step_m must be > 0, compliance_m and overtravel_m >= 0")


class PoseEstimator(Protocol):
    """What the controller asks each frame: the in-hand pose ``T_ee_object`` (4, 4) after
    ``frame``. ``truth`` is the simulator's state at that frame, for test estimators only (the
    ground truth, or the truth with an offset); a real estimator must use ``frame`` alone."""

    def __call__(self, frame: Frame, truth: EpisodeState) -> np.ndarray: ...


# The sensors: a frame (what a robot would log) of a state, with its index and attempt (1-based).
Observe = Callable[[EpisodeState, int, int], Frame]


def ground_truth_estimator(offset: np.ndarray | None = None) -> PoseEstimator:
    """An estimator that returns the true in-hand pose, moved by ``offset`` (a pose in ee axes
    about the object's origin, as ``episode.apply_offset``) when given."""

    def estimate(frame: Frame, truth: EpisodeState) -> np.ndarray:
        return truth.T_ee_object if offset is None else apply_offset(offset, truth.T_ee_object)

    return estimate


def robot_frame(state: EpisodeState, index: int, attempt: int) -> Frame:
    """The frame a robot without cameras or tactile sensors logs: end effector, contact and
    finger opening (enough for ``ground_truth_estimator``)."""
    return Frame(index=index, stamp_ns=state.stamp_ns, T_world_ee=state.T_world_ee, contact=state.contact,
                 finger_opening_m=state.finger_opening_m)


@dataclass
class Attempt:
    """One descent: its frames (first frame of its approach or back-off to its last), how it
    ended (``OUTCOMES``: ``inserted``; ``stalled`` above the depth; ``believed_inserted``: the
    estimate said inserted, the truth is not), the true depth of the leading face below the
    mouth at its end [m], and the estimate's error at its alignment (the last hover frame):
    horizontal translation in receptacle axes [m] and rotation [deg]."""

    index: int
    first_frame: int
    last_frame: int
    outcome: str
    depth_m: float
    align_error_m: float
    align_error_deg: float


@dataclass
class InsertionResult:
    """One grasp in closed loop: ``success`` (ground truth), the attempts, every frame's state,
    and the simulated time from the first frame to the end of the successful descent [s]."""

    success: bool
    attempts: list[Attempt]
    states: list[EpisodeState] = field(repr=False)
    time_to_insert_s: float | None
    rate_hz: float

    @property
    def frames(self) -> int:
        return len(self.states)


def inserted_depth_m(T_world_receptacle: np.ndarray, T_world_object: np.ndarray) -> float:
    """How far the object's leading face (its frame's origin) is below the receptacle mouth [m]."""
    return float(-(se3.invert(T_world_receptacle) @ T_world_object)[2, 3])


def run_insertion(
    T_world_receptacle: np.ndarray,
    insertion_depth_m: float,
    T_ee_object_nominal: np.ndarray,
    object_mesh: trimesh.Trimesh,
    collider: Collider,
    episode: EpisodeOptions,
    controller: ControllerOptions,
    rng: np.random.Generator,
    estimate: PoseEstimator,
    observe: Observe = robot_frame,
    squeeze: str = "pads",
) -> InsertionResult:
    """Insert one grasp in closed loop (the module docstring); ``rng`` draws the grasp, the
    start pose and the slip, ``observe`` makes each frame for ``estimate``; ``squeeze`` where the
    pads close on the part after the grasp offset and each slip (``episode.centre_between_pads``;
    the object's ``grasp_squeeze``, as ``mvtop simulate`` does)."""
    c = controller
    T_ee_obj, pad_l, pad_r = centre_between_pads(
        apply_offset(sample_grasp_offset(episode, rng), T_ee_object_nominal), object_mesh,
        episode.indentation_m, squeeze)
    dt_ns = int(round(1e9 / episode.rate_hz))
    target_depth = insertion_depth_m + c.overtravel_m

    def aligned(T_ee_obj_est: np.ndarray, height_m: float) -> np.ndarray:
        """The end effector that puts the estimated object ``height_m`` above the mouth, aligned."""
        return T_world_receptacle @ se3.make_pose(np.eye(3), [0.0, 0.0, height_m]) @ se3.invert(T_ee_obj_est)

    states: list[EpisodeState] = []
    estimates: list[np.ndarray] = []

    def record(T_ee: np.ndarray, attempt: int, force: float = 0.0) -> np.ndarray:
        """Log a frame at ``T_ee``, let the estimator see it; returns the estimate."""
        d = collider.distance(T_ee @ T_ee_obj)
        st = EpisodeState(episode.start_time_ns + len(states) * dt_ns, T_ee.copy(), T_ee_obj.copy(), pad_l, pad_r,
                          d < CONTACT_DISTANCE_M, d, force)
        states.append(st)
        est = np.asarray(estimate(observe(st, len(states) - 1, attempt), st), dtype=np.float64)
        estimates.append(est)
        return est

    # the start: the nominal grasp's object above the receptacle, shifted and turned at random
    T_start = aligned(T_ee_object_nominal, c.approach_height_m)
    T_start[:2, 3] += rng.uniform(-c.start_lateral_m, c.start_lateral_m, size=2)
    swing = Rotation.from_euler("z", rng.uniform(-c.start_yaw_deg, c.start_yaw_deg), degrees=True).as_matrix()
    T_start[:3, :3] = swing @ T_start[:3, :3]
    est = record(T_start, 1)
    for k in range(1, c.approach_frames):
        a = 0.5 - 0.5 * np.cos(np.pi * k / (c.approach_frames - 1))  # smooth start and stop
        est = record(_move(states[-1].T_world_ee, se3.interpolate(T_start, aligned(est, c.hover_height_m), a),
                           T_ee_obj, collider), 1)

    attempts: list[Attempt] = []
    success, time_to_insert = False, None
    first_frame = 0
    for attempt in range(1, c.attempts + 1):
        for _ in range(c.align_frames):
            est = record(_move(states[-1].T_world_ee, aligned(est, c.hover_height_m), T_ee_obj, collider), attempt)
        T_align = aligned(est, 0.0)  # the descent keeps this alignment
        truth, guess = states[-1].T_world_object, states[-1].T_world_ee @ est
        err_xy = (se3.invert(T_world_receptacle)[:3, :3] @ (truth[:3, 3] - guess[:3, 3]))[:2]
        align_err_m, align_err_deg = float(np.linalg.norm(err_xy)), float(
            np.degrees(se3.rotation_angle(truth[:3, :3], guess[:3, :3])))

        height = c.hover_height_m
        outcome = None
        while outcome is None:
            height = max(height - c.descent_step_m, -target_depth)
            T_cmd = T_align.copy()
            T_cmd[2, 3] += height
            T_prev = states[-1].T_world_ee
            if states[-1].contact:  # slip in the grasp under contact
                T_ee_obj, pad_l, pad_r, T_prev = _slip(T_ee_obj, T_prev, object_mesh, collider, episode, rng,
                                                       squeeze)
            T_ee = _move(T_prev, T_cmd, T_ee_obj, collider)
            contact = collider.distance(T_ee @ T_ee_obj) < CONTACT_DISTANCE_M
            force = 5.0 + rng.normal(0.0, 0.3) if contact else rng.normal(0.0, 0.05)
            est = record(T_ee, attempt, force)
            made = T_prev[2, 3] - T_ee[2, 3]
            stalled = states[-1].contact and made < c.stall_fraction * c.descent_step_m
            if not stalled and height > -target_depth:
                continue
            est_depth = inserted_depth_m(T_world_receptacle, T_ee @ est)
            true_depth = inserted_depth_m(T_world_receptacle, states[-1].T_world_object)
            if est_depth >= insertion_depth_m - c.compliance_m or not stalled:
                ok = true_depth >= insertion_depth_m - c.compliance_m
                outcome = "inserted" if ok else "believed_inserted"
            else:
                outcome = "stalled"
        attempts.append(Attempt(attempt, first_frame, len(states) - 1, outcome, true_depth, align_err_m,
                                align_err_deg))
        if outcome != "stalled":
            success = outcome == "inserted"
            if success:
                time_to_insert = len(states) / episode.rate_hz
            break
        if attempt == c.attempts:
            break
        first_frame = len(states)
        T_low = states[-1].T_world_ee
        for k in range(1, c.backoff_frames + 1):  # back off, still estimating, towards the re-aligned hover pose
            est = record(_move(states[-1].T_world_ee, se3.interpolate(T_low, aligned(est, c.hover_height_m),
                                                                      k / c.backoff_frames),
                               T_ee_obj, collider), attempt + 1)
    return InsertionResult(success, attempts, states, time_to_insert, episode.rate_hz)


def _move(T_from: np.ndarray, T_to: np.ndarray, T_ee_obj: np.ndarray, collider: Collider) -> np.ndarray:
    """The end effector moved from ``T_from`` (object collision-free) towards ``T_to`` along
    ``se3.interpolate``, stopped at the first contact: the last collision-free pose, found by
    bisection."""
    if collider.distance(T_to @ T_ee_obj) > 0.0:
        return T_to.copy()
    lo, hi = 0.0, 1.0  # fraction of the way; lo is free, hi collides
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        if collider.distance(se3.interpolate(T_from, T_to, mid) @ T_ee_obj) > 0.0:
            lo = mid
        else:
            hi = mid
    return se3.interpolate(T_from, T_to, lo) if lo > 0.0 else T_from.copy()


def _slip(T_ee_obj: np.ndarray, T_world_ee: np.ndarray, mesh: trimesh.Trimesh, collider: Collider,
          episode: EpisodeOptions, rng: np.random.Generator, squeeze: str = "pads"):
    """The part slipped in the grasp under contact (``episode.slip_*``): the new in-hand pose
    and pad positions, and the end effector lifted until the part is free (a slip into the
    receptacle pushes the gripper back); a slip that 3 mm of lift cannot free is not taken."""
    slip = se3.make_pose(
        Rotation.from_rotvec(np.radians(rng.normal(0.0, episode.slip_rotation_deg, 3))).as_matrix(),
        rng.normal(0.0, episode.slip_translation_m, 3),
    )
    T_new, pad_l, pad_r = centre_between_pads(apply_offset(slip, T_ee_obj), mesh, episode.indentation_m, squeeze)
    T = T_world_ee.copy()
    for _ in range(_LIFT_MAX_STEPS + 1):
        if collider.distance(T @ T_new) > 0.0:
            return T_new, pad_l, pad_r, T
        T[2, 3] += _LIFT_STEP_M
    _, pad_l, pad_r = centre_between_pads(T_ee_obj, mesh, episode.indentation_m, squeeze)
    return T_ee_obj, pad_l, pad_r, T_world_ee
