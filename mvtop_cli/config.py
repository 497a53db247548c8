"""Typed, validated YAML configuration: one frozen dataclass per section, checked once at load.

``load_config(path)`` rejects unknown keys with a did-you-mean suggestion, checks types and
ranges, resolves mesh paths relative to the config file, and raises one ``ConfigError``
naming the file and the dotted key. Units are in the key names (``_m`` metres, ``_deg``
degrees, ``_s`` seconds); inside mvtop everything is SI.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from .errors import ConfigError
from .geometry import se3

MODALITIES = ("vision", "tactile", "contact")


def _rng(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, doc: str = "") -> dict:
    """Field metadata: allowed numeric range (inclusive unless ``lo_open``) and a doc string."""
    return {"lo": lo, "hi": hi, "lo_open": lo_open, "doc": doc}


@dataclass(frozen=True)
class PoseSpec:
    """A rigid transform ``T_parent_child``: translation ``xyz_m`` [m] and a rotation given
    either as ``rpy_deg`` [deg] or as a unit quaternion ``quat_xyzw`` (x, y, z, w; the ROS
    order, as in a TF message or ``render-masks --pose-ee``), not both.

    ``rpy_deg = (r, p, y)`` is extrinsic x-y-z: rotate by r about the parent's x axis, then
    by p about the parent's y axis, then by y about the parent's z axis, ``R = Rz(y) Ry(p)
    Rx(r)``; the same matrix as ROS's ``tf2::Quaternion::setRPY(r, p, y)`` and URDF's
    ``<origin rpy>``.
    """

    xyz_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_rng(-1000.0, 1000.0))
    rpy_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_rng(-360.0, 360.0))
    quat_xyzw: tuple[float, float, float, float] | None = field(default=None, metadata={
        **_rng(-1.0, 1.0, doc="unit quaternion (x, y, z, w), instead of rpy_deg"), "omit_if_none": True})

    def __post_init__(self) -> None:
        if self.quat_xyzw is None:
            return
        if any(v != 0.0 for v in self.rpy_deg):
            raise ValueError("give the rotation as rpy_deg or as quat_xyzw, not both")
        norm = math.sqrt(sum(v * v for v in self.quat_xyzw))
        if abs(norm - 1.0) > 1e-3:
            raise ValueError(f"quat_xyzw: expected a unit quaternion (x, y, z, w), got norm {norm:.6g}")

    def matrix(self) -> np.ndarray:
        """The (4, 4) pose."""
        from scipy.spatial.transform import Rotation

        if self.quat_xyzw is not None:
            q = np.asarray(self.quat_xyzw, dtype=float)
            return se3.from_quat_xyzw(q / np.linalg.norm(q), np.asarray(self.xyz_m, dtype=float))
        R = Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_matrix()
        return se3.make_pose(R, np.asarray(self.xyz_m, dtype=float))

    @staticmethod
    def from_matrix(T: np.ndarray) -> "PoseSpec":
        import warnings

        from scipy.spatial.transform import Rotation

        with warnings.catch_warnings():  # at +-90 deg pitch the angles are not unique; any set is exact
            warnings.simplefilter("ignore", UserWarning)
            rpy = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("xyz", degrees=True)
        return PoseSpec(tuple(float(v) for v in np.asarray(T)[:3, 3]), tuple(float(v) for v in rpy))


@dataclass(frozen=True)
class ContinuousSymmetry:
    """Rotation by any angle about ``axis`` through ``point_m`` (object frame) maps the mesh
    onto itself (a round peg, a cylinder): the symmetry group is these rotations composed
    with ``object.symmetries``."""

    axis: tuple[float, float, float] = field(default=(0.0, 0.0, 1.0), metadata=_rng(-1.0, 1.0))
    point_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=_rng(-10.0, 10.0))

    def unit_axis(self) -> np.ndarray:
        a = np.asarray(self.axis, dtype=np.float64)
        return a / np.linalg.norm(a)


@dataclass(frozen=True)
class DirectionalClearance:
    """Clearance that differs by direction: the free travel [m] of the inserted object along
    the object frame's lateral axes, ``(towards -x, towards +x)`` and ``(towards -y, towards +y)``."""

    x_m: tuple[float, float] = field(metadata=_rng(0.0, 0.01, lo_open=True))
    y_m: tuple[float, float] = field(metadata=_rng(0.0, 0.01, lo_open=True))


@dataclass(frozen=True)
class ObjectConfig:
    """The grasped object: its CAD model and insertion tolerance."""

    name: str
    mesh: Path
    units: Literal["m", "mm"] = "m"
    clearance_m: float | None = field(default=None, metadata=_rng(0.0, 0.01, lo_open=True, doc=(
        "per-side clearance in the receptacle; without it eval reports insertable as n/a")))
    insertion_depth_m: float = field(default=0.0, metadata=_rng(0.0, 0.2))
    symmetries: tuple[PoseSpec, ...] = field(
        default=(), metadata={"doc": "transforms S (besides the identity) with mesh == S applied to mesh"}
    )
    continuous_symmetry: ContinuousSymmetry | None = field(
        default=None, metadata={"doc": "an axis about which every rotation maps the mesh onto itself"}
    )
    directional_clearance: DirectionalClearance | None = field(
        default=None, metadata={"doc": "clearance per direction; clearance_m is then its smallest value"}
    )
    render_mesh: Path | None = field(
        default=None, metadata={"doc": "a simplified copy of mesh (same frame and units) for the mask renderer"}
    )


@dataclass(frozen=True)
class EnvironmentMesh:
    """A fixed or gripper-mounted mesh: it occludes the object and (if ``collide``) bounds it."""

    name: str
    mesh: Path
    frame: str = "world"
    pose: PoseSpec = PoseSpec()
    units: Literal["m", "mm"] = "m"
    collide: bool = True
    occlude: bool = True


@dataclass(frozen=True)
class CameraSensor:
    """An RGB camera: image and CameraInfo topics and its optical frame."""

    name: str
    image_topic: str
    info_topic: str
    frame: str | None = None
    mask_topic: str | None = field(default=None, metadata={"omit_if_none": True, "doc": (
        "with masking.camera.backend 'topic': the object masks an external segmenter publishes for this camera "
        "(sensor_msgs/Image mono8 or mono16, or a png CompressedImage; 0 = background)")})
    weight: float | None = field(default=None, metadata=_rng(
        0.0, 1.0, doc="eq. 2 weight; default an equal part of the modality's share; 0 switches the sensor off"))


@dataclass(frozen=True)
class TactileSensor:
    """A GelSight-style tactile sensor: images, optional indentation depth, and gel geometry."""

    name: str
    image_topic: str
    info_topic: str
    depth_topic: str | None = None
    frame: str | None = None
    gel_distance_m: float = field(default=0.025, metadata=_rng(0.0, 0.2, lo_open=True))
    weight: float | None = field(default=None, metadata=_rng(
        0.0, 1.0, doc="eq. 2 weight; default an equal part of the modality's share; 0 switches the sensor off"))


@dataclass(frozen=True)
class SensorsConfig:
    """The cameras and tactile sensors, and how eq. 2 splits the score between the modalities."""

    cameras: tuple[CameraSensor, ...] = ()
    tactile: tuple[TactileSensor, ...] = ()
    tactile_share: float = field(default=0.5, metadata=_rng(
        0.0, 1.0, doc="eq. 2: the tactile sensors' share of the score when cameras and touch are both enabled "
                      "(the cameras hold the rest); each modality keeps its share on frames where the other "
                      "has no image"))


@dataclass(frozen=True)
class TopicsConfig:
    """Topic names of the non-image streams."""

    tf: str = "/tf"
    tf_static: str = "/tf_static"
    contact: str | None = "/contact"
    joint_states: str | None = "/joint_states"
    wrench: str | None = None
    ground_truth: str | None = "/ground_truth/object_pose"


@dataclass(frozen=True)
class FramesConfig:
    world: str = "world"
    ee: str = "ee"


@dataclass(frozen=True)
class RobotConfig:
    """The robot model, for logs that record joint states but not the end effector's TF."""

    urdf: Path | None = field(default=None, metadata={"doc": "URDF whose links are added to TF from /joint_states"})


@dataclass(frozen=True)
class GraspPrior:
    """Prior over the object in the end effector, ``T_ee_object``: nominal pose and spread."""

    pose: PoseSpec = PoseSpec()
    distribution: Literal["uniform", "gaussian"] = "uniform"
    translation_m: float = field(default=0.003, metadata=_rng(0.0, 0.1, doc="half-width (uniform) or sigma (gaussian)"))
    rotation_deg: float = field(default=10.0, metadata=_rng(0.0, 180.0))


@dataclass(frozen=True)
class BackendConfig:
    """A masking backend chosen by name, with backend-specific options."""

    backend: str
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class MaskingConfig:
    """Masking backends per modality; ``prompt_when_converged`` switches the cameras to the
    paper's promptable mode (a mask prompted at the estimate) once the belief has converged."""

    camera: BackendConfig = BackendConfig("classical")
    tactile: BackendConfig = BackendConfig("difference")
    prompt_when_converged: bool = False
    candidates: int = field(default=96, metadata=_rng(
        1, 100_000, doc="Algorithm 1: the best-weighted particles whose renders choose among the camera proposals"))
    grabcut_prompt: Literal["belief", "prior"] = field(default="belief", metadata={
        "doc": "what seeds the camera GrabCut proposal: the weighted belief (its likely poses' silhouettes), or the "
               "grasp prior (prior_samples fixed poses in the end-effector frame, so no belief shapes the mask: "
               "the belief only chooses among the proposals)"})
    prior_samples: int = field(default=256, metadata=_rng(
        8, 100_000, doc="fixed grasp-prior poses whose silhouettes make the prior's window in each camera (where "
                        "search.mode_check takes its proposals), and, with grabcut_prompt: prior or camera_evidence: "
                        "colour, seed the GrabCut or the colour histograms"))
    camera_evidence: Literal["masks", "colour"] = field(default="masks", metadata={
        "doc": "what a camera's eq. 2 term compares each pose with: the observed mask of Algorithm 1-2 (masks), or "
               "each pixel's object probability from colour histograms of the object and its surroundings, learned "
               "where the grasp prior places the part, scored as a soft IoU (masking/colour.py; no belief enters it)"})
    colour_bins: int = field(default=16, metadata=_rng(
        2, 256, doc="with camera_evidence: colour, histogram levels per RGB channel (a divisor of 256)"))
    colour_margin_px: float = field(default=24.0, metadata=_rng(
        0.0, 1000.0, doc="with camera_evidence: colour, image pixels around the grasp prior's window from which "
                         "the background histogram is learned too"))
    belief_band_px: int = field(default=1, metadata=_rng(
        0, 64, doc="with grabcut_prompt: belief, the belief's GrabCut proposal leaves at least this many ROI pixels "
                   "on either side of the belief's outline to the image's colours and edges (0: only where the likely "
                   "poses disagree, so a tight belief draws its own outline)"))
    contact_exclusion_m: float | None = field(default=None, metadata=_rng(
        0.0, 0.05, doc="camera pixels that show a world-fixed colliding environment surface (the receptacle) within "
                       "this distance [m] of the box the grasp prior spans carry no evidence: left out of the "
                       "observed masks and of every pose's render (where the part rests on a surface of its own "
                       "colour no outline separates them), in frames where that surface shows the part's colours "
                       "(contact_exclusion_overlap); null: every pixel counts"))
    contact_exclusion_overlap: float = field(default=0.55, metadata=_rng(
        0.0, 1.0, doc="with contact_exclusion_m: the Bhattacharyya coefficient of the colour histograms "
                      "(colour_bins) of the part (pixels every fixed grasp-prior pose covers) and of the surface "
                      "beside it (the excluded pixels no prior pose covers) from which that surface counts as "
                      "showing the part's colours"))
    converged_translation_m: float = field(default=0.0005, metadata=_rng(
        0.0, 0.1, doc="with prompt_when_converged: the belief's RMS translation spread below which it counts "
                      "as converged"))
    converged_rotation_deg: float = field(default=1.5, metadata=_rng(
        0.0, 180.0, doc="with prompt_when_converged: the same for the RMS rotation spread"))
    tactile_depth_threshold_m: float = field(default=2e-5, metadata=_rng(
        0.0, 0.01, lo_open=True, doc="indentation below this is undeformed gel (tactile masks from a depth topic, "
                                    "and the rendered tactile masks)"))
    tactile_depth_tolerance_m: float | None = field(default=None, metadata=_rng(
        0.0, 0.01, doc="with a tactile depth topic: a pose's gel contact leaves out, as missed, the observed contact "
                       "pixels it presses deeper than the sensor measured there plus this tolerance [m] (a binary "
                       "contact mask cannot tell a part pressed deeper from one pressed as measured); null: the "
                       "masks alone"))


@dataclass(frozen=True)
class FilterConfig:
    """Particle filter parameters (Algorithms 3-4, eq. 1)."""

    num_particles: int = field(default=500, metadata=_rng(1, 1_000_000))
    temperature: float = field(default=0.003, metadata=_rng(
        0.0, 10.0, lo_open=True, doc="softmax temperature tau of eq. 1"))
    sigma_low_translation_m: float = field(default=0.0001, metadata=_rng(0.0, 0.1))
    sigma_low_rotation_deg: float = field(default=0.1, metadata=_rng(0.0, 180.0))
    sigma_high_translation_m: float = field(default=0.0001, metadata=_rng(0.0, 0.1))
    sigma_high_rotation_deg: float = field(default=0.25, metadata=_rng(0.0, 180.0))
    translation_axis_scale: tuple[float, float, float] = field(default=(1.0, 1.0, 1.0), metadata=_rng(
        0.0, 1.0, doc=("multipliers of both translation sigmas along the end effector's x, y, z axes (the motion "
                       "model, Algorithm 4): below 1 on an axis the grasp does not slip along")))
    resampling: Literal["systematic", "stratified", "multinomial", "residual"] = "systematic"
    ess_threshold: float = field(default=0.5, metadata=_rng(0.0, 1.0))
    refine_iterations: int = field(default=8, metadata=_rng(0, 1000, doc="0: Algorithm 3's single importance update; "
                                                                          "more: the tempered SMC refinement's stages"))
    tracking_particles: int = field(default=0, metadata=_rng(0, 1_000_000, doc=(
        "tracking mode: a later frame that is no check frame, keeps the previous frame's contact state and follows a "
        "settled frame (no search, switch, collapse, forced tempering, warning of suspicion or rival) is refined into "
        "this many particles, drawn from the density of all predicted ones; every other frame into num_particles "
        "again; 0: off, every frame num_particles (README: Tracking mode)")))
    posterior_sweeps: int | None = field(default=4, metadata=_rng(1, 1000, doc=(
        "at most this many Metropolis sweeps of the refinement at the posterior (tempering exponent 1, counting the "
        "sweep of the stage that reaches it); the iterations left after them are not run (the first frame's 24 "
        "iterations reach it in 4-6 stages); null: all of them run (README: Sweeps at the posterior)")))
    refine_shrink: float = field(default=0.5, metadata=_rng(
        0.0, 1.0, lo_open=True, doc="factor of the refinement's Metropolis proposal scale when its acceptance is low"))
    refine_target_ess_fraction: float = field(default=0.5, metadata=_rng(
        0.0, 1.0, lo_open=True, doc="fraction of the ESS each adaptive tempering stage keeps"))
    floor_translation_m: float = field(default=5e-5, metadata=_rng(
        0.0, 0.01, lo_open=True,
        doc="smallest kernel / proposal sigma per axis of the refinement, and of the jump check"))
    floor_rotation_deg: float = field(default=0.05, metadata=_rng(0.0, 10.0, lo_open=True))
    ess_collapse_fraction: float = field(default=0.01, metadata=_rng(
        0.0, 1.0, doc="an ESS below this fraction of the particles (at least 2) counts as collapsed"))
    collapse_retry_iterations: int = field(default=24, metadata=_rng(
        0, 1000,
        doc="a frame whose ESS collapsed is redone with max(this, 3 x refine_iterations) stages; 0: only flag it"))
    jump_sigmas: float = field(default=5.0, metadata=_rng(
        0.0, 1000.0, lo_open=True, doc="estimate_jump: a move beyond this many RMS spreads of the predicted belief"))
    roi_size_px: int = field(default=128, metadata=_rng(16, 1024, doc=(
        "longest side of a camera's scoring window [ROI pixels]: a window whose image extent is longer is "
        "downsampled k-fold (k = ceil(extent / this)); 256 scores the plug's and shaft peg's windows over a spread "
        "belief at full resolution: fewer far-off plug estimates, a worse shaft peg median (README: Scoring window)")))
    tactile_roi_size_px: int = field(default=128, metadata=_rng(16, 1024, doc=(
        "the same for a tactile sensor's window (a 320 px GelSight pad: k = 3 at 128, 0.17 mm a ROI pixel); 256 "
        "lifted the plug and lowered conn1 (README: Scoring window)")))
    camera_full_weight_px: float = field(default=0.0, metadata=_rng(0.0, 1e7, doc=(
        "a camera whose observed mask covers fewer image pixels than this has its eq. 2 weight scaled by the "
        "fraction it covers, the modality's other cameras taking up the rest of its share: an IoU over a few "
        "pixels swings from 0 to 1 with a pixel's shift (conn2's side view, nearly hidden in its receptacle: "
        "README, Small camera masks); 0: every camera at its full weight")))
    seed: int = field(default=0, metadata=_rng(0, 2**63 - 1))
    fold_symmetries: bool = field(default=True, metadata={"doc": (
        "summarise the belief modulo object.symmetries and object.continuous_symmetry: each particle is taken "
        "as the member of its symmetry class closest to the reference before the estimate, covariance, jump "
        "check and refinement chart (estimator/symmetry.py); off: the particles as they are")})


@dataclass(frozen=True)
class SearchConfig:
    """The cross-entropy searches around the filter: the first frame's search of the grasp
    prior, every later frame's local re-search check (a frame is redone from the searched poses
    when they beat the belief by ``recheck_margin``), and the dissent, rival and mode checks."""

    init_factor: int = field(default=6, metadata=_rng(
        1, 1000, doc="prior samples per particle in the first-frame search and the dissent and rival checks' searches"))
    first_frame_iteration_factor: int = field(default=3, metadata=_rng(
        1, 100,
        doc="refinement iterations on the first frame (and after a re-search), in units of filter.refine_iterations"))
    first_frame_rounds: int = field(default=10, metadata=_rng(0, 1000, doc=(
        "rounds of the first frame's search of the grasp prior (the refinement continues from its basin; README: Ten "
        "rounds of the first frame's search)")))
    rounds: int = field(default=12, metadata=_rng(0, 1000, doc=(
        "rounds of the rival check's and the dissent search's searches of the grasp prior (their best poses are "
        "judged as found)")))
    elite_fraction: float = field(default=0.1, metadata=_rng(0.0, 1.0, lo_open=True))
    widen: float = field(default=1.5, metadata=_rng(
        0.0, 100.0, lo_open=True, doc="sigma factor of the elite's Gaussian"))
    floor_translation_m: float = field(default=5e-5, metadata=_rng(0.0, 0.01, lo_open=True))
    floor_rotation_deg: float = field(default=0.05, metadata=_rng(0.0, 10.0, lo_open=True))
    bound: float = field(default=2.0, metadata=_rng(
        0.0, 100.0, lo_open=True, doc="searches stay within this many grasp-prior half-widths (twice as many sigmas "
                                      "for a gaussian prior) of the nominal grasp"))
    recheck_sigma_translation_m: float = field(default=0.001, metadata=_rng(
        0.0, 0.1, doc="per-axis widening of the belief that starts each frame's re-search"))
    recheck_sigma_rotation_deg: float = field(default=3.0, metadata=_rng(0.0, 180.0))
    recheck_rounds: int = field(default=3, metadata=_rng(0, 1000))
    recheck_margin: float = field(default=10.0, metadata=_rng(
        0.0, 1e6, doc="nats by which a searched pose must beat the estimate and the best particle to redo the frame"))
    rival_every: int = field(default=10, metadata=_rng(
        0, 100_000, doc="every this many frames (frame index + 1 a multiple of it) a fresh search of the grasp prior, "
                        "with its own generator, looks for another pose that explains the frame about as well as the "
                        "estimate (a rival mode; flag rival_mode); 0: never"))
    rival_margin: float = field(default=3.0, metadata=_rng(
        0.0, 1e6, doc="nats below the estimate's log-likelihood within which the search's best pose is a rival"))
    rival_translation_m: float = field(default=0.001, metadata=_rng(
        0.0, 1.0, doc="a rival lies farther than this from the estimate (modulo the part's symmetries) ..."))
    rival_rotation_deg: float = field(default=3.0, metadata=_rng(0.0, 180.0, doc="... or turned farther than this"))
    disagreement_margin: float | None = field(default=8.0, metadata=_rng(
        0.0, 1e6, doc="on the first frame, each sensor is left out in turn: when the others (and the contact term) "
                      "prefer one of the search's poses beyond rival_translation_m / rival_rotation_deg to the "
                      "estimate by at least this many nats, the sensors disagree and the estimate rests on that one "
                      "sensor (warning and flag sensors_disagree, the covariance the grasp prior's spread for the "
                      "run); null: no such check"))
    check_at_contact: bool = field(default=True, metadata={
        "doc": "with the contact modality, also run the rival and mode checks on the first frame of each contact (a "
               "frame in contact after one without, not the first frame): a part that a wrong mode stopped on the "
               "receptacle's rim is searched for while the contact says where it is"})
    mode_check: bool = field(default=True, metadata={
        "doc": "with touch and camera proposals (not recorded masks or colour evidence), each rival check also "
               "searches the grasp prior with every pose choosing its own camera mask among the belief-free proposals "
               "(Algorithm 2 per pose); when that search's best pose lies beyond rival_translation_m / "
               "rival_rotation_deg and beats the estimate by mode_margin nats, the belief is in a wrong mode whose "
               "own masks agree with it: the frame is redone from the searched poses (flag mode_switch); when it "
               "scores from rival_margin below the estimate to mode_margin above it, it is a rival (flag rival_mode)"})
    rival_beside_mode_check: bool = field(default=False, metadata={
        "doc": "also run the rival check on the frames the mode check searches; off (default): there the mode check "
               "alone judges rivals: a standing one is searched for where it now is and ruled out when nothing there "
               "comes within rival_margin of the estimate, on the frame's likelihood, or for a held-back switch on "
               "the belief-free terms (README: Rival modes; the rival check's search is about a third of a run's "
               "poses)"})
    mode_margin: float = field(default=5.0, metadata=_rng(
        0.0, 1e6, doc="nats by which the mode check's best pose, and then the frame redone from it, must beat the "
                      "estimate to replace it (the other searches use recheck_margin)"))
    mode_init_factor: int = field(default=2, metadata=_rng(
        1, 1000, doc="prior samples per particle in the mode check's search (a far better mode is found with fewer "
                     "than the first frame's search needs to place the estimate)"))
    mode_rounds: int = field(default=8, metadata=_rng(0, 1000, doc="rounds of the mode check's search"))
    mode_history_frames: int = field(default=9, metadata=_rng(
        0, 1000, doc="the mode check also scores its best pose, and then the redone frame's estimate, against the "
                     "estimate on up to this many earlier frames since the last contact, each pose choosing among "
                     "their belief-free proposals: in free air the grasp holds, so one in-hand pose explains them "
                     "all, and a switch needs the margin over them and the frame together (contact, or a log "
                     "without a contact signal, empties them); 0: the frame alone"))
    dissent: bool = field(default=True, metadata={
        "doc": "when a sensor disagrees with the estimate the others agree on (consistency.low_iou / consensus_iou), "
               "search the grasp prior for the poses that sensor explains before its weight is scaled down, and redo "
               "the frame from them when they beat the estimate by recheck_margin"})


@dataclass(frozen=True)
class EdgesConfig:
    """The camera contour term (beyond the paper; ``estimator/edges.py``): the image gradient
    across each camera's projected object contour, added to eq. 6's log-likelihood."""

    gain: float = field(default=0.0, metadata=_rng(
        0.0, 1000.0, doc="nats per 100 px of contour per unit of gradient across it above the background level "
                         "(CIE Lab units per image pixel, summed over L*, a*, b*), per camera; 0: no contour term"))
    background_factor: float = field(default=2.0, metadata=_rng(
        0.0, 100.0, doc="a contour sample is evidence for the pose above this many times the window's median "
                        "gradient, against it below"))
    blur_sigma_px: float = field(default=0.8, metadata=_rng(
        0.0, 20.0, doc="Gaussian smoothing of the image before its derivatives [image pixels]"))
    spacing_px: float = field(default=1.0, metadata=_rng(
        0.05, 100.0, doc="distance between samples along the projected contour [ROI pixels]"))
    crease_deg: float = field(default=30.0, metadata=_rng(
        0.0, 180.0, doc="mesh edges whose faces meet at more than this angle are read too where both faces "
                        "face the camera (a visible edge inside the outline) [deg]"))
    occluder_margin_px: float = field(default=2.0, metadata=_rng(
        0.0, 100.0, doc="contour samples this close across the contour to an outline of the occluders "
                        "(fingers, receptacle, table) are not read: they would read that outline [ROI pixels]"))
    occluder_depth_step: float = field(default=0.01, metadata=_rng(
        0.0, 1.0, lo_open=True, doc="an occluders' outline is where their inverse depth changes by more than this "
                                    "fraction between neighbouring pixels"))


@dataclass(frozen=True)
class ExtrinsicsConfig:
    """The camera extrinsics check (beyond the paper; ``estimator/extrinsics.py``): on each
    camera's first image, the environment meshes' projected outlines against the image's edges,
    with the camera turned about its optical centre."""

    mode: Literal["correct", "warn", "off"] = field(default="correct", metadata={"doc": (
        "a camera the known scene lines up with only turned: correct (use it turned so for the run, warning "
        "camera_extrinsics), warn (use it as recorded, warning camera_extrinsics and the run reported suspect) "
        "or off (no check)")})
    range_deg: float = field(default=4.0, metadata=_rng(
        0.0, 30.0, lo_open=True, doc="the turns searched about each optical axis, +- [deg]"))
    step_deg: float = field(default=0.25, metadata=_rng(
        0.0, 10.0, lo_open=True, doc="the search grid's step about each axis [deg]"))
    coarse_downsample: int = field(default=4, metadata=_rng(
        1, 64, doc="a second start searches all three axes at this many times step_deg, on the image downsampled "
                   "this many times (and its blur this many times wider); 1: at full resolution; none when the "
                   "image's width or height is not a multiple of it"))
    min_step_deg: float = field(default=0.01, metadata=_rng(
        0.0, 10.0, lo_open=True, doc="the local refinement halves its step down to this [deg]"))
    min_turn_deg: float = field(default=0.3, metadata=_rng(
        0.0, 30.0, lo_open=True, doc="a camera is misaligned when the best turn is at least this [deg] ..."))
    min_gain: float = field(default=0.2, metadata=_rng(
        0.0, 1.0, lo_open=True, doc="... and adds at least this share of its outline score"))
    min_samples: int = field(default=200, metadata=_rng(
        1, 10_000_000, doc="contour samples of the known scene in the image needed to judge a camera"))
    mesh_tolerance_deg: float = field(default=0.35, metadata=_rng(
        0.0, 30.0, doc="a misaligned camera is corrected only when each environment mesh (with a quarter of "
                       "min_samples) lines up on its own with a turn that moves its pixels less than this from where "
                       "the joint turn puts them (RMS, as an angle) [deg]: else more than a turn is off"))
    background_factor: float = field(default=2.0, metadata=_rng(
        0.0, 100.0, doc="a contour sample counts for the alignment above this many times the image's median "
                        "gradient, against it below"))
    blur_sigma_px: float = field(default=1.0, metadata=_rng(
        0.0, 20.0, doc="Gaussian smoothing of the image before its derivatives [image pixels]"))
    spacing_px: float = field(default=1.0, metadata=_rng(
        0.05, 100.0, doc="distance between samples along the projected contour edges [image pixels]"))


@dataclass(frozen=True)
class ConsistencyConfig:
    """The sensor consistency watch (``filter.health.SensorConsistency``): a sensor whose
    mask disagrees with the estimate the others agree on for ``frames`` frames in a row has
    its eq. 2 weight scaled by ``factor`` for the rest of the run."""

    low_iou: float = field(default=0.5, metadata=_rng(
        0.0, 1.0, doc="a sensor disagrees below this IoU at the estimate"))
    consensus_iou: float = field(default=0.7, metadata=_rng(
        0.0, 1.0, doc="... while the others' median IoU is at least this"))
    frames: int = field(default=5, metadata=_rng(1, 100_000))
    factor: float = field(default=0.01, metadata=_rng(0.0, 1.0))
    min_others: int = field(default=2, metadata=_rng(
        1, 1000, doc="informative full-weight sensors needed to judge one"))
    max_fraction: float = field(default=0.5, metadata=_rng(
        0.0, 1.0, doc="at most this fraction of the sensors is scaled down"))


@dataclass(frozen=True)
class OutputConfig:
    """What the track files hold beyond the estimates."""

    track_particles: int = field(default=200, metadata=_rng(0, 1_000_000, doc="particles per frame in track.mcap"))
    evidence_step_translation_m: float = field(default=0.0005, metadata=_rng(
        1e-6, 0.1, doc="the evidence diagnostic moves the estimate this far along each axis (estimator/evidence.py)"))
    evidence_step_rotation_deg: float = field(default=0.5, metadata=_rng(
        1e-4, 90.0, doc="... and turns it this far about each axis"))
    covariance: Literal["particles", "particles_and_evidence"] = field(default="particles_and_evidence", metadata={
        "doc": "the reported covariance: the particles' spread alone, or plus the likelihood's widths at the "
               "estimate (estimator/evidence.py; the grasp prior's spread on an axis the evidence does not pin)"})
    evidence_width_factor: float = field(default=3.0, metadata=_rng(
        0.0, 1000.0, lo_open=True,
        doc="with particles_and_evidence: the likelihood's widths are taken this many times wider in the "
            "reported covariance (calibrated on benchmark seeds 3000-3005, checked on 5000-5009: README)"))
    evidence_profile: bool | Literal["without_cameras"] = field(default="without_cameras", metadata={"doc": (
        "on the check frames (search.rival_every, contact onsets) also measure the likelihood's profile widths "
        "(each axis with the other five searched: estimator/evidence.py) and report the wider of them and the "
        "probe's in the covariance until the next check, an axis the profile leaves open counting as open for "
        "suspect_unpinned_fraction; the estimates are the same either way. "
        "without_cameras: only on check frames no camera evidence enters (touch alone, whose pads leave "
        "ridges the one-axis probe misses: README, Reading the evidence)")})
    evidence_profile_translation_m: float = field(default=0.002, metadata=_rng(
        1e-6, 0.1, lo_open=True, doc="the profile's farthest offset along each translation axis (also at 1/4 and 1/2)"))
    evidence_profile_rotation_deg: float = field(default=4.0, metadata=_rng(
        1e-4, 90.0, lo_open=True, doc="... and about each rotation axis"))
    evidence_profile_scale: float = field(default=0.5, metadata=_rng(
        0.0, 100.0, lo_open=True,
        doc="the profile's search of the other coordinates starts this many probe steps wide"))
    evidence_profile_population: int = field(default=48, metadata=_rng(
        2, 100_000, doc="poses per offset and round of the profile's search (36 offsets share a call)"))
    evidence_profile_rounds: int = field(default=5, metadata=_rng(1, 1000, doc="rounds of the profile's search"))
    suspect_unpinned_fraction: float | None = field(default=0.4, metadata=_rng(
        0.0, 1.0, lo_open=True,
        doc="a suspect_estimate warning when at least this fraction of the frames with evidence left the pose open: "
            "some axis the evidence diagnostic (the probe, and the latest profile where measured) does not pin, or a "
            "rival mode no check has ruled out yet (filter/health.py; chosen on benchmark seeds 3000-3005 and "
            "5000-5009, checked on 6000-6004: README); null: never"))


@dataclass(frozen=True)
class ContactConfig:
    """Contact likelihood (eq. 8-9): margin tau_c and softness sigma_d; the non-penetration
    factor under contact (tau_p, sigma_p; beyond the paper)."""

    margin_m: float = field(default=0.0, metadata=_rng(-0.01, 0.01))
    softness_m: float = field(default=0.00005, metadata=_rng(0.0, 0.01, lo_open=True))
    sdf_resolution_m: float = field(default=0.00025, metadata=_rng(0.0, 0.01, lo_open=True))
    penetration_tolerance_m: float = field(default=0.0001, metadata=_rng(
        0.0, 0.01, doc="under contact, a pose sunk this deep into the environment loses half its weight "
                       "(contact/likelihood.py: log_penetration_likelihood, beyond the paper)"))
    penetration_softness_m: float | None = field(default=0.00005, metadata=_rng(
        0.0, 0.01, lo_open=True, doc="how fast the weight falls with deeper penetration; null: no "
                                     "non-penetration factor (eq. 8-9 alone)"))
    force_on_n: float = field(default=2.0, metadata=_rng(0.0, 10000.0, doc="with topics.wrench: contact starts here"))
    force_off_n: float = field(default=1.0, metadata=_rng(0.0, 10000.0, doc="with topics.wrench: contact ends here"))


@dataclass(frozen=True)
class Config:
    """A whole mvtop configuration. ``source`` is the file it was loaded from."""

    object: ObjectConfig
    sensors: SensorsConfig
    environment: tuple[EnvironmentMesh, ...] = ()
    topics: TopicsConfig = TopicsConfig()
    frames: FramesConfig = FramesConfig()
    robot: RobotConfig = RobotConfig()
    grasp_prior: GraspPrior = GraspPrior()
    masking: MaskingConfig = MaskingConfig()
    filter: FilterConfig = FilterConfig()
    search: SearchConfig = SearchConfig()
    consistency: ConsistencyConfig = ConsistencyConfig()
    edges: EdgesConfig = EdgesConfig()
    extrinsics: ExtrinsicsConfig = ExtrinsicsConfig()
    contact: ContactConfig = ContactConfig()
    output: OutputConfig = OutputConfig()
    modalities: tuple[Literal["vision", "tactile", "contact"], ...] = MODALITIES
    sync_tolerance_s: float = field(default=0.02, metadata=_rng(0.0, 10.0))
    source: Path | None = field(default=None, metadata={"internal": True})

    def required_topics(self) -> dict[str, str]:
        """Topics this config reads, mapped to the ROS 2 type each must have. With a URDF the
        moving frames come from the joint states, so /tf is read when present but not required."""
        req = {self.topics.tf_static: "tf2_msgs/msg/TFMessage"}
        if self.robot.urdf is None:
            req = {self.topics.tf: "tf2_msgs/msg/TFMessage", **req}
        for cam in self.sensors.cameras:
            req[cam.image_topic] = _image_type(cam.image_topic)
            req[cam.info_topic] = "sensor_msgs/msg/CameraInfo"
            if cam.mask_topic:
                req[cam.mask_topic] = _image_type(cam.mask_topic)
        for tac in self.sensors.tactile:
            req[tac.image_topic] = _image_type(tac.image_topic)
            req[tac.info_topic] = "sensor_msgs/msg/CameraInfo"
            if tac.depth_topic:
                req[tac.depth_topic] = "sensor_msgs/msg/Image"
        if self.robot.urdf is not None and self.topics.joint_states:
            req[self.topics.joint_states] = "sensor_msgs/msg/JointState"
        if self.topics.contact and "contact" in self.modalities:
            req[self.topics.contact] = "std_msgs/msg/Bool"
        elif self.topics.wrench and "contact" in self.modalities:
            req[self.topics.wrench] = "geometry_msgs/msg/WrenchStamped"
        return req

    def required_frames(self) -> list[str]:
        """TF frames this config needs (sensor frames named explicitly, world, ee, mesh frames)."""
        frames = [self.frames.world, self.frames.ee]
        frames += [s.frame for s in (*self.sensors.cameras, *self.sensors.tactile) if s.frame]
        frames += [e.frame for e in self.environment]
        return list(dict.fromkeys(frames))


def _image_type(topic: str) -> str:
    return "sensor_msgs/msg/CompressedImage" if topic.rstrip("/").endswith("compressed") else "sensor_msgs/msg/Image"


# ---------------------------------------------------------------------------------------------
# Generic validation over the dataclasses above.

class _Invalid(Exception):
    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key
        self.message = message


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if tp is type(None):
        return "null"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_type_name(args[0])}"
        return f"a list of {len(args)} numbers" if all(a is float for a in args) else f"a list of {len(args)} items"
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false", Path: "a file path"}.get(
        tp, str(tp)
    )


def _convert(value: Any, tp: Any, key: str, base: Path) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(value, a, key, base)
            except _Invalid as err:
                errors.append(err)
        if len(errors) == 1:
            raise errors[0]
        raise _Invalid(key, f"expected {_type_name(tp)}, got {value!r}")
    if origin is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            hint = difflib.get_close_matches(str(value), [str(a) for a in allowed], n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else ""
            raise _Invalid(key, f"expected {_type_name(tp)}, got {value!r}{extra}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise _Invalid(key, f"expected {_type_name(tp)}, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{key}[{i}]", base) for i, v in enumerate(value))
        if len(value) != len(args):
            raise _Invalid(key, f"expected {_type_name(tp)}, got {len(value)} items")
        return tuple(_convert(v, a, f"{key}[{i}]", base) for i, (v, a) in enumerate(zip(value, args)))
    if origin is dict:
        if not isinstance(value, dict):
            raise _Invalid(key, f"expected a mapping, got {value!r}")
        return dict(value)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key, base)
    if tp is bool:
        if not isinstance(value, bool):
            raise _Invalid(key, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Invalid(key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Invalid(key, f"expected a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond the float range
            number = math.inf
        if not math.isfinite(number):
            raise _Invalid(key, f"expected a finite number, got {value!r}")
        return number
    if tp is str:
        if not isinstance(value, str) or not value:
            raise _Invalid(key, f"expected a non-empty string, got {value!r}")
        if not value.isprintable():  # names, topics and frames: a control character is a typo
            raise _Invalid(key, f"expected a string without control characters, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str) or not value or "\x00" in value:
            raise _Invalid(key, f"expected a file path, got {value!r}")
        try:
            p = Path(value).expanduser()
        except RuntimeError as err:  # '~user' of an unknown user
            raise _Invalid(key, f"expected a file path, got {value!r} ({err})") from None
        return p if p.is_absolute() else (base / p)
    if tp is Any:
        return value
    raise TypeError(f"unsupported config type {tp!r} at {key}")


def _check_range(value: Any, meta: dict, key: str) -> None:
    lo, hi = meta.get("lo"), meta.get("hi")
    if value is None or (lo is None and hi is None):
        return
    if isinstance(value, tuple):  # a fixed-size list of numbers: the range holds for each
        for i, v in enumerate(value):
            _check_range(v, meta, f"{key}[{i}]")
        return
    if lo is not None and (value < lo or (meta.get("lo_open") and value == lo)):
        op = ">" if meta.get("lo_open") else ">="
        raise _Invalid(key, f"expected a value {op} {lo}, got {value!r}")
    if hi is not None and value > hi:
        raise _Invalid(key, f"expected a value <= {hi}, got {value!r}")


def _build(cls: type, data: Any, prefix: str, base: Path) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise _Invalid(prefix or "(top level)", f"expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    for k in data:
        if k not in fields:
            hint = difflib.get_close_matches(str(k), list(fields), n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else f" (expected one of: {', '.join(fields)})"
            raise _Invalid(_join(prefix, key_text(k)), f"unknown key{extra}")
    kwargs = {}
    for name, f in fields.items():
        key = _join(prefix, name)
        if name in data:
            value = _convert(data[name], hints[name], key, base)
            _check_range(value, f.metadata, key)
            kwargs[name] = value
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise _Invalid(key, "missing required key")
    try:
        return cls(**kwargs)
    except ValueError as err:  # a dataclass's own cross-field check (__post_init__)
        raise _Invalid(prefix or "(top level)", str(err)) from None


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def key_text(key: Any) -> str:
    """A mapping key as it appears in a dotted key: as written when printable, else quoted
    with escapes (a key holding a line break must not break the one-line error)."""
    text = str(key)
    return text if text.isprintable() and text.strip() == text and text else repr(text)


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except (OSError, ValueError):  # e.g. a name too long for the file system
        return False


def _check_semantics(cfg: Config) -> None:
    """Cross-field checks that the types alone cannot express."""
    names = [s.name for s in (*cfg.sensors.cameras, *cfg.sensors.tactile)]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _Invalid("sensors", f"sensor names must be unique, {dup[0]!r} is used twice")
    if not names:
        raise _Invalid("sensors", "expected at least one camera or tactile sensor")
    if all(s.weight == 0.0 for s in (*cfg.sensors.cameras, *cfg.sensors.tactile)):
        raise _Invalid("sensors", "every sensor has weight 0, so no image would score a pose "
                                  "(leave 'weight' out for the default share)")
    if len(set(cfg.modalities)) != len(cfg.modalities):
        raise _Invalid("modalities", "a modality is listed twice")
    if 256 % cfg.masking.colour_bins:
        raise _Invalid("masking.colour_bins", f"expected a divisor of 256 (e.g. 16), got {cfg.masking.colour_bins}")
    if not cfg.modalities:
        raise _Invalid("modalities", f"expected at least one of {', '.join(MODALITIES)}")
    meshes = [("object.mesh", cfg.object.mesh)] + [("object.render_mesh", cfg.object.render_mesh)] * bool(
        cfg.object.render_mesh) + [
        (f"environment[{i}].mesh", e.mesh) for i, e in enumerate(cfg.environment)
    ]
    for key, path in meshes:
        if not _is_file(path):
            raise _Invalid(key, f"mesh file not found: {path}")
    if cfg.robot.urdf is not None and not _is_file(cfg.robot.urdf):
        raise _Invalid("robot.urdf", f"URDF file not found: {cfg.robot.urdf}")
    if cfg.contact.force_off_n >= cfg.contact.force_on_n:
        raise _Invalid("contact.force_off_n", "expected a value below contact.force_on_n (hysteresis)")
    _check_object(cfg.object)
    _check_recorded_masks(cfg)
    f = cfg.filter
    if f.sigma_high_translation_m < f.sigma_low_translation_m:
        raise _Invalid("filter.sigma_high_translation_m", "expected a value >= filter.sigma_low_translation_m")


TOPIC_BACKEND = "topic"  # masking.camera.backend that reads the cameras' recorded masks (mask_topic)


def _check_recorded_masks(cfg: Config) -> None:
    """``masking.camera.backend: topic`` reads each camera's masks from its ``mask_topic``
    (every camera needs one); its only option is ``label``, the label id of the object
    (default: every non-zero label)."""
    spec = cfg.masking.camera
    cams = cfg.sensors.cameras
    if spec.backend != TOPIC_BACKEND:
        for i, cam in enumerate(cams):
            if cam.mask_topic:
                raise _Invalid(f"sensors.cameras[{i}].mask_topic", f"recorded masks are read only with "
                               f"masking.camera.backend: {TOPIC_BACKEND} (the backend is {spec.backend!r})")
        return
    for i, cam in enumerate(cams):
        if not cam.mask_topic:
            raise _Invalid(f"sensors.cameras[{i}].mask_topic", f"camera {cam.name!r} needs the topic of its recorded "
                           f"object masks (masking.camera.backend is {TOPIC_BACKEND!r})")
    unknown = sorted(set(spec.options) - {"label"})
    if unknown:
        raise _Invalid(f"masking.camera.options.{unknown[0]}", f"unknown option of the {TOPIC_BACKEND!r} backend "
                                                               "(expected only 'label')")
    label = spec.options.get("label")
    if label is not None and (isinstance(label, bool) or not isinstance(label, int) or not 1 <= label <= 65535):
        raise _Invalid("masking.camera.options.label", f"expected the object's label id, an integer 1-65535 "
                                                       f"(or no label: every non-zero pixel), got {label!r}")


def _check_object(obj: ObjectConfig) -> None:
    """The continuous symmetry's axis is a direction; a directional clearance's smallest value
    is the per-side ``clearance_m`` the reports quote."""
    if obj.continuous_symmetry is not None and np.linalg.norm(obj.continuous_symmetry.axis) < 1e-6:
        raise _Invalid("object.continuous_symmetry.axis", "expected a non-zero direction")
    d = obj.directional_clearance
    if d is not None and abs(min(*d.x_m, *d.y_m) - obj.clearance_m) > 1e-9:
        raise _Invalid("object.clearance_m", f"expected the smallest value of object.directional_clearance, "
                                             f"{min(*d.x_m, *d.y_m)!r}, got {obj.clearance_m!r}")


def parse_section(cls: type, data: Any, source: Path | str, base_dir: Path) -> Any:
    """Validate ``data`` as the dataclass ``cls`` with the config's rules (unknown keys with a
    suggestion, types, ranges; relative paths against ``base_dir``): for other YAML files
    (object files) that follow them. ``ConfigError`` names ``source`` and the dotted key."""
    try:
        return _build(cls, data, "", Path(base_dir))
    except _Invalid as err:
        raise ConfigError(f"{source}: {err.key}: {err.message}") from None


def invalid(source: Path | str, key: str, message: str) -> ConfigError:
    """The one-line ``ConfigError`` of a cross-field check: ``"{source}: {key}: {message}"``."""
    return ConfigError(f"{source}: {key}: {message}")


def parse_config(data: Any, source: Path | str = "<config>", base_dir: Path | None = None) -> Config:
    """Validate already-parsed YAML ``data``; relative paths resolve against ``base_dir``."""
    source = Path(source)
    base = base_dir if base_dir is not None else source.parent
    try:
        cfg = _build(Config, data, "", base)
        _check_semantics(cfg)
    except _Invalid as err:
        raise ConfigError(f"{source}: {err.key}: {err.message}") from None
    return dataclasses.replace(cfg, source=source)


def parse_settings(items: typing.Sequence[str], option: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` overrides (a command's repeatable ``--set``) as ``{dotted key: value}``.

    KEY is a dotted config key (``contact.softness_m``; a list item by its index,
    ``sensors.cameras.0.name``); VALUE is read as YAML (``500`` an int, ``[1, 2]`` a list),
    and a number written in exponent form without a point (``5e-5``, a string to YAML 1.1) as
    a float. The keys are checked when the settings are applied to a config
    (``apply_settings``, then ``parse_config``)."""
    settings: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        parts = key.split(".")
        if not sep or not key or not all(parts):
            raise ConfigError(f"{option}: expected KEY=VALUE with a dotted config key, e.g. "
                              f"contact.softness_m=1.0e-04, got {item!r}")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            raise ConfigError(f"{option} {key}: expected a YAML value, got {text!r}") from None
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                pass
        if key in settings:
            raise ConfigError(f"{option} {key}: given twice")
        settings[key] = value
    return settings


def apply_settings(data: Any, settings: typing.Mapping[str, Any]) -> Any:
    """A copy of parsed YAML config ``data`` with each dotted key of ``settings`` set to its
    value (``parse_settings``); a missing section is created, so that an unknown key reaches
    ``parse_config``'s did-you-mean check. A key that passes through a value that is not a
    section (or a list index out of range) is a ``ConfigError`` naming it (as ``--set KEY``)."""
    data = copy.deepcopy(data) if data is not None else {}
    for key, value in settings.items():
        parts = key.split(".")
        node = data
        for depth, part in enumerate(parts):
            last = depth == len(parts) - 1
            where = ".".join(parts[:depth]) or "the config"
            if isinstance(node, list):
                if not part.isdigit() or int(part) >= len(node):
                    raise ConfigError(f"--set {key}: {where} is a list of {len(node)}; expected an index "
                                      f"0-{len(node) - 1}, got {part!r}")
                index: Any = int(part)
            elif isinstance(node, dict):
                index = part
                if not last and node.get(part) is None:
                    node[part] = {}
            else:
                raise ConfigError(f"--set {key}: {where} is a value, not a section")
            if last:
                node[index] = value
            else:
                node = node[index]
    return data


def load_config(path: Path | str, settings: typing.Mapping[str, Any] | None = None) -> Config:
    """Load and validate a YAML config file, with ``settings`` (``parse_settings``) applied
    over it; raises ``ConfigError`` naming file and dotted key."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read config file ({err})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ConfigError(f"{path}: invalid YAML{where}: {problem}") from None
    if settings:
        data = apply_settings(data, settings)
    return parse_config(data, path, path.resolve().parent)


def config_to_dict(cfg: Config, relative_to: Path | None = None) -> dict:
    """The resolved config as plain YAML-ready data (paths absolute, or relative to ``relative_to``)."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v) if not f.metadata.get("internal")
                    and not (f.metadata.get("omit_if_none") and getattr(v, f.name) is None)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, Path):
            p = v.resolve()
            if relative_to is not None:
                try:
                    import os

                    return os.path.relpath(p, relative_to.resolve())
                except ValueError:
                    pass
            return str(p)
        return v

    return conv(cfg)


def dump_config(cfg: Config, relative_to: Path | None = None) -> str:
    """YAML text of the resolved config (every default filled in)."""
    return yaml.safe_dump(config_to_dict(cfg, relative_to), sort_keys=False)
