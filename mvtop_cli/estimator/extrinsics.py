"""The camera extrinsics check (beyond the paper): does the known scene line up with each image?

Every camera sees, besides the part, meshes whose poses the log fixes without any estimate:
the receptacle and the board in ``world``, the fingers on their TF frames. With the camera's
recorded extrinsics right, their projected outlines run along the image's edges; with the camera
turned by a degree (about 5 mm at 0.3 m, ten pixels) they miss them, and the part's estimate
follows the turned camera while every sensor seems to agree (docs/robustness.md). The check
reads only the image and the TF tree: no mask, no estimate, no belief enters it.

``scene_outline_score`` sums, over the visible samples of the environment meshes' projected
contour edges (``render.contour``, every ``spacing_px`` image pixels), the colour gradient across
the edge minus ``background_factor`` times the image's typical gradient: the contour term's
log-likelihood ratio of "an edge here" (``estimator/edges.py``), for the scene instead of the
part. ``align_camera`` turns the camera about its optical centre (a rotation ``turn`` in its
optical frame, ``T_sensor_mesh -> Exp(turn) @ T_sensor_mesh``) over a grid of +-``range_deg``
about x and y, then about z, and over a coarser grid about all three axes on the image
downsampled ``coarse_downsample`` times, then refines the better start locally down to
``min_step_deg``, and keeps the turn that scores best. A camera is misaligned when that turn is
at least ``min_turn_deg`` and raises the score by at least ``min_gain`` of its best value
(``CameraAlignment.misaligned``).

What follows (``extrinsics.mode``): ``correct`` uses the camera at ``T_world_sensor @
Exp(turn)^-1`` for the whole run and says so (warning ``camera_extrinsics``); ``warn`` only says
so and reports the run as suspect (flag ``camera_extrinsics``, the covariance the grasp prior's
spread about the estimate). A turn at the edge of the searched range is never corrected: the
true one may lie beyond it, so the run is reported as suspect whatever the mode.

A turn is corrected only where it is the whole error: each environment mesh with at least a
quarter of ``min_samples`` contour samples is lined up on its own, from the joint turn, and its
own turn must move the pixels it covers by less than ``mesh_tolerance_deg`` (RMS, as an angle)
from where the joint turn puts them (``_mesh_spread``). A camera moved along its optical axis
scales the scene about the image centre: a turn then lines up the far board's outline and leaves
the fingers, near the centre, wanting theirs 0.6-1.5 deg away (camera moved 5-10 mm, cube), where
that turn would put the part 6-12 pixels off. Such a camera is reported as with ``warn``
and not corrected (``CameraAlignment.one_turn``). A camera moved across its axis is much like a
turn at the scene's depth, and the meshes agree on one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..config import ExtrinsicsConfig
from ..filter.health import warning
from ..geometry import se3
from ..records import Frame, SensorImage
from ..render.roi import Roi
from .edges import EdgeImage
from .scene import SceneModel

# The local refinement stops after this many moves (it moves at most range / step per scale).
_MAX_MOVES = 200


@dataclass(frozen=True)
class CameraAlignment:
    """The extrinsics check of one camera on one frame.

    ``turn_deg`` (3,) [deg]: the rotation vector, in the camera's optical frame, that lines the
    known scene up with the image best (``Exp(turn) @ T_sensor_mesh``); ``score_recorded`` /
    ``score_turned`` the scene's outline score [gradient units above the background, summed
    over samples] with the recorded extrinsics and with the turn; ``samples`` the contour
    samples read with the recorded extrinsics; ``at_edge`` the turn lies on the searched
    range's edge (the true one may be larger); ``mesh_spread_deg`` how far apart the meshes want
    the camera turned (``_mesh_spread``) [deg] (None when not measured: the camera is not
    misaligned); ``one_turn`` that spread is within
    ``extrinsics.mesh_tolerance_deg``, so one turn corrects the whole error; ``misaligned`` the
    check's verdict; ``corrected`` the run uses the turned camera (``extrinsics.mode: correct``)."""

    camera: str
    frame: int
    turn_deg: tuple[float, float, float]
    score_recorded: float
    score_turned: float
    samples: int
    at_edge: bool
    mesh_spread_deg: float | None
    one_turn: bool
    misaligned: bool
    corrected: bool

    @property
    def angle_deg(self) -> float:
        """The turn's angle [deg]."""
        return float(np.linalg.norm(self.turn_deg))

    @property
    def gain(self) -> float:
        """The share of the turned score the turn adds: 0 when the recorded extrinsics score best."""
        return (self.score_turned - self.score_recorded) / max(abs(self.score_turned), 1e-12)

    @property
    def suspect(self) -> bool:
        """A misaligned camera the run did not correct: the estimate rests on its wrong pose."""
        return self.misaligned and not self.corrected

    def corrected_pose(self, T_world_sensor: np.ndarray) -> np.ndarray:
        """The camera's pose (4, 4) in ``world`` turned as the check found (``turned_camera``)."""
        return turned_camera(T_world_sensor, self.turn_deg)

    def warning(self) -> dict:
        """The ``camera_extrinsics`` warning record of a misaligned camera (frame: the check's)."""
        x, y, z = self.turn_deg
        if self.corrected:
            then = "the run used it turned so (extrinsics.mode: correct)"
        elif self.at_edge:
            then = ("the turn lies at the edge of the searched range (extrinsics.range_deg), so the true one may be "
                    "larger and it was not corrected: the estimate may be far off and its covariance is the grasp "
                    "prior's spread about it")
        elif not self.one_turn:
            then = (f"the environment meshes line up with turns up to {self.mesh_spread_deg:.2f} deg apart, so more "
                    "than a turn is off (the camera moved, or a mesh misplaced in the config) and it was not "
                    "corrected: the estimate may be far off and its covariance is the grasp prior's spread about it")
        else:
            then = ("the estimate used the recorded extrinsics (extrinsics.mode: warn) and may be far off; its "
                    "covariance is the grasp prior's spread about it")
        return warning(
            self.frame, "camera_extrinsics",
            f"camera {self.camera!r}: the known scene (environment meshes) lines up with its image only with the "
            f"camera turned {self.angle_deg:.2f} deg ({x:.2f}, {y:.2f}, {z:.2f} deg about its optical x, y, z "
            f"axes; outline score {self.score_recorded:.0f} -> {self.score_turned:.0f}): its extrinsics are likely "
            f"off; {then}; recalibrate the camera",
            sensor=self.camera, turn_deg=[float(v) for v in self.turn_deg], angle_deg=self.angle_deg,
            gain=self.gain, mesh_spread_deg=self.mesh_spread_deg, ratio=self.angle_deg, corrected=self.corrected,
        )

    def suspect_warning(self) -> dict:
        """The run's ``suspect_estimate`` record for a misaligned camera left uncorrected."""
        return warning(
            None, "suspect_estimate",
            f"camera {self.camera!r} looks turned {self.angle_deg:.2f} deg from its recorded extrinsics (frame "
            f"{self.frame}) and the estimate used them as recorded: it may be far off; its covariance is the grasp "
            "prior's spread about it (flag camera_extrinsics); check it against another measurement before "
            "relying on it",
            sensor=self.camera, angle_deg=self.angle_deg,
        )


def turned_camera(T_world_sensor: np.ndarray, turn_deg) -> np.ndarray:
    """A camera pose (4, 4) in ``world`` turned about its optical centre by the check's ``turn_deg``
    (3,) [deg]: ``T_world_sensor @ Exp(turn)^-1``, so the scene at ``Exp(turn) @ T_sensor_mesh``,
    where the image showed it, is where the turned camera sees it."""
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_matrix(np.radians(np.asarray(turn_deg, dtype=np.float64)))
    return T_world_sensor @ se3.invert(T)


def scene_outline_score(scene: SceneModel, img: SensorImage, frame_pose: Callable[[str], np.ndarray],
                        turns_rad: np.ndarray, settings: ExtrinsicsConfig, edges: EdgeImage | None = None,
                        meshes: list[tuple[str, np.ndarray]] | None = None,
                        roi: Roi | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The environment meshes' outline score in camera image ``img`` with the camera turned by
    each rotation vector of ``turns_rad`` (N, 3) [rad, the camera's optical frame].

    ``meshes``: ``(mesh_id, T_sensor_mesh)`` pairs with the recorded extrinsics, by default every
    occluding environment mesh (``SceneModel.occluders``: ``environment[i].occlude``, the ones the
    renderer holds; ``frame_pose(tf_frame)`` gives ``T_world_frame`` at the image's stamp for
    meshes on moving frames), read without occlusion between them. Returns (score (N,) [CIE Lab
    units per pixel above ``background_factor`` times the image's median gradient, summed over
    the samples], samples (N,) int: the contour samples inside the image). ``roi``: the whole
    image, possibly downsampled, that ``edges`` were made for (default: at full resolution),
    samples every ``spacing_px`` of its pixels."""
    roi = roi if roi is not None else Roi.full(img.camera)
    edges = edges if edges is not None else EdgeImage.of(img.image, roi, settings.blur_sigma_px)
    meshes = meshes if meshes is not None else scene.occluders(img.T_world_sensor, frame_pose)
    level = settings.background_factor * edges.background
    turns = np.repeat(np.eye(4)[None], len(turns_rad), axis=0)
    turns[:, :3, :3] = se3.rotvec_to_matrix(np.asarray(turns_rad, dtype=np.float64).reshape(-1, 3))
    score = np.zeros(len(turns))
    samples = np.zeros(len(turns), dtype=np.int64)
    for mesh_id, T_sensor_mesh in meshes:
        s, n = scene.renderer.contour_gradient(mesh_id, turns @ T_sensor_mesh, img.camera, roi, edges.gx, edges.gy,
                                               None, settings.spacing_px, 0.0)
        score += s - level * n
        samples += n
    return score, samples


def align_camera(score: Callable[[np.ndarray], np.ndarray], settings: ExtrinsicsConfig,
                 coarse: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, float, bool]:
    """The turn (3,) [deg] that maximises ``score(turns_rad (N, 3)) -> (N,)``. Two starts: a grid
    over +-``range_deg`` about x and y at ``step_deg`` (z at 0), then about z at the best x, y;
    and, with ``coarse`` (the score on a downsampled image, ``coarse_downsample``), a grid about
    all three axes at ``coarse_downsample`` times the step, then a full-resolution grid of +-2
    steps about its best (a roll the first start's grid leaves out can line a cluttered scene up
    elsewhere; alone, it misses some turns the x/y grid finds: README, Cameras whose extrinsics are
    off). From the better of the two, a local search of the 26 neighbours, moving while one
    scores better and halving the step down to ``min_step_deg``. Returns the turn, its score and
    whether it lies on the range's edge. The recorded extrinsics (turn 0) are a grid point of the
    first start and win its ties, and the second replaces it only when it scores higher, so the
    best turn never scores below them."""
    r, step = settings.range_deg, settings.step_deg

    def grid(half_width: float, spacing: float, axes: int) -> np.ndarray:
        axis = np.linspace(-half_width, half_width, 2 * int(round(half_width / spacing)) + 1)
        g = np.stack(np.meshgrid(*[axis] * axes, indexing="ij"), axis=-1).reshape(-1, axes)
        g = np.concatenate([g, np.zeros((len(g), 3 - axes))], axis=1)
        return np.concatenate([np.zeros((1, 3)), g])  # turn 0 first: the first of equals wins

    def best_of(turns_deg: np.ndarray, fn=score) -> tuple[np.ndarray, float]:
        turns_deg = np.clip(turns_deg, -r, r)
        values = fn(np.radians(turns_deg))
        k = int(np.argmax(values))
        return turns_deg[k], float(values[k])

    best, _ = best_of(grid(r, step, 2))
    line = np.repeat(best[None], 2 * int(round(r / step)) + 2, axis=0)
    line[1:, 2] = np.linspace(-r, r, len(line) - 1)
    best, value = best_of(line)
    if coarse is not None:
        found, _ = best_of(grid(r, settings.coarse_downsample * step, 3), coarse)
        found, v = best_of(found + grid(2 * step, step, 3)[1:])
        if v > value:
            best, value = found, v
    best, value = refine_turn(score, best, value, settings)
    return best, value, bool(np.any(np.abs(best) >= r - step / 2.0))


def refine_turn(score: Callable[[np.ndarray], np.ndarray], start_deg: np.ndarray, value: float,
                settings: ExtrinsicsConfig) -> tuple[np.ndarray, float]:
    """From ``start_deg`` (3,) scoring ``value``: the local search of ``align_camera``, the 26
    neighbours at half ``step_deg``, moving while one scores better and halving the step down to
    ``min_step_deg``, within +-``range_deg``. Returns the turn [deg] and its score."""
    r = settings.range_deg
    best, h, moves = np.asarray(start_deg, dtype=np.float64), settings.step_deg / 2.0, 0
    offsets = np.stack(np.meshgrid(*[np.array([0.0, -1.0, 1.0])] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    while h >= settings.min_step_deg - 1e-12 and moves < _MAX_MOVES:
        candidates = np.clip(best + h * offsets, -r, r)  # offsets[0] is the centre: it wins ties
        values = score(np.radians(candidates))
        k = int(np.argmax(values))
        if values[k] > value and not np.array_equal(candidates[k], best):
            best, value, moves = candidates[k], float(values[k]), moves + 1
        else:
            h /= 2.0
    return best, value


def check_camera(scene: SceneModel, name: str, img: SensorImage, frame_index: int,
                 frame_pose: Callable[[str], np.ndarray], settings: ExtrinsicsConfig) -> CameraAlignment | None:
    """The extrinsics check of camera ``name`` on its image ``img`` of frame ``frame_index``;
    None when the known scene shows fewer than ``min_samples`` contour samples in the image
    (nothing to judge by)."""
    edges = EdgeImage.of(img.image, Roi.full(img.camera), settings.blur_sigma_px)

    def score(turns_rad: np.ndarray) -> np.ndarray:
        return scene_outline_score(scene, img, frame_pose, turns_rad, settings, edges)[0]

    recorded, samples = scene_outline_score(scene, img, frame_pose, np.zeros((1, 3)), settings, edges)
    if samples[0] < settings.min_samples:
        return None
    k = settings.coarse_downsample
    small = None if img.camera.width % k or img.camera.height % k else Roi(0, 0, img.camera.width,
                                                                           img.camera.height, 1.0 / k)
    if small is not None:
        small_edges = EdgeImage.of(img.image, small, k * settings.blur_sigma_px)

        def coarse(turns_rad: np.ndarray) -> np.ndarray:
            return scene_outline_score(scene, img, frame_pose, turns_rad, settings, small_edges, roi=small)[0]

    turn, turned, at_edge = align_camera(score, settings, None if small is None else coarse)
    found = CameraAlignment(name, frame_index, tuple(float(v) for v in turn), float(recorded[0]), turned,
                            int(samples[0]), at_edge, mesh_spread_deg=None, one_turn=True, misaligned=False,
                            corrected=False)
    if not (found.angle_deg >= settings.min_turn_deg and found.gain >= settings.min_gain):
        return found
    spread = _mesh_spread(scene, img, frame_pose, turn, settings, edges)
    one_turn = spread <= settings.mesh_tolerance_deg
    return replace(found, mesh_spread_deg=spread, one_turn=one_turn, misaligned=True,
                   corrected=one_turn and not at_edge and settings.mode == "correct")


def _mesh_spread(scene: SceneModel, img: SensorImage, frame_pose: Callable[[str], np.ndarray], turn_deg: np.ndarray,
                 settings: ExtrinsicsConfig, edges: EdgeImage) -> float:
    """How far apart the environment meshes want the camera turned [deg]: for each mesh with at
    least a quarter of ``min_samples`` contour samples at the joint turn ``turn_deg``, the turn
    that lines it up on its own (``refine_turn`` from the joint one), and how far that moves the
    image where the mesh is (the RMS displacement over the pixels it covers at the joint turn,
    as an angle at the focal length: a roll a small mesh pins poorly, compensated by a pan, moves
    its pixels little); the largest over the meshes (0 when none has enough samples)."""
    roi = Roi.full(img.camera)
    K = np.asarray(img.camera.K, dtype=np.float64)
    R_joint = se3.rotvec_to_matrix(np.radians(turn_deg))
    T_joint = np.eye(4)
    T_joint[:3, :3] = R_joint
    spread = 0.0
    for mesh in scene.occluders(img.T_world_sensor, frame_pose):
        def score(turns_rad, mesh=mesh):
            return scene_outline_score(scene, img, frame_pose, turns_rad, settings, edges, [mesh])[0]

        value, n = scene_outline_score(scene, img, frame_pose, np.radians(turn_deg)[None], settings, edges, [mesh])
        if 4 * n[0] < settings.min_samples:
            continue
        own, _ = refine_turn(score, turn_deg, float(value[0]), settings)
        mesh_id, T_sensor_mesh = mesh
        rows, cols = np.nonzero(scene.renderer.render_masks(mesh_id, (T_joint @ T_sensor_mesh)[None], img.camera,
                                                            roi)[0])
        if len(rows) == 0:
            continue
        pixels = np.stack([cols, rows, np.ones_like(cols)]).astype(np.float64)  # (3, P) homogeneous
        rays = (se3.rotvec_to_matrix(np.radians(own)) @ R_joint.T) @ (np.linalg.inv(K) @ pixels)
        moved = K @ rays
        shift_px = np.sqrt(np.mean(np.sum((moved[:2] / moved[2] - pixels[:2]) ** 2, axis=0)))
        spread = max(spread, float(np.degrees(np.arctan(shift_px / K[0, 0]))))
    return spread


def corrected_frame(frame: Frame, alignments: dict[str, CameraAlignment | None]) -> Frame:
    """``frame`` with every camera the check corrected at its turned pose (``corrected_pose``);
    the frame itself when there is none."""
    fixed = {name: replace(img, T_world_sensor=alignments[name].corrected_pose(img.T_world_sensor))
             for name, img in frame.cameras.items()
             if alignments.get(name) is not None and alignments[name].corrected}
    return replace(frame, cameras={**frame.cameras, **fixed}) if fixed else frame
