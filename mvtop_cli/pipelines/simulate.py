"""``mvtop simulate``: render one insertion episode and write it as a ROS 2 MCAP log.

The log carries what a real setup records (see docs/log-format.md) plus the ground-truth
object pose: two RGB cameras, two GelSight-like tactile sensors (image and indentation depth),
TF, finger joint states, the contact flag, the wrench, and ``/ground_truth/object_pose``.
The same options and seed give a byte-identical file.

Options reproduce how real setups record (docs/recording.md): raw or compressed images, lens
distortion, the end effector at the end of a robot's TF chain or only as joint states plus
a URDF (``KINEMATICS``), and sensors at different rates with dropped images and unsynchronised
capture times (``SensorTiming``).

``mask_topics`` also records what an external segmenter would publish: each camera image's
true visible object mask on ``/cameras/<name>/mask`` (mono8, 255 = object; png on
``.../mask/compressed``), optionally degraded by ``mask_error_px``. Harder camera scenes
(``sim.hard_scene``): ``shadows``, ``glossy``, ``clutter``, ``light_change``; ``HARD_SCENE``
turns them all on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from ..errors import MvtopError
from ..geometry import se3
from ..io.mcap_writer import LogWriter
from ..sim import gripper as grip
from ..sim import hard_scene as hard
from ..sim import robot
from ..sim.camera_render import CameraSceneRenderer, Material, PhotometricOptions, apply_camera_effects
from ..sim.episode import Collider, EpisodeOptions, EpisodeState, plan_episode, state_at
from ..sim.object_file import resolve_object
from ..sim.scene import board_mesh, camera_placements, receptacle_pose, table_mesh
from ..sim.tactile import make_background, render_tactile_image
from ..sim.timing import SensorTiming, capture_schedule

TACTILE_SIDES = ("left", "right")
INDENTATION_STEP_M = 1e-6
FINGER_JOINTS = robot.FINGER_JOINTS
# How the log gives the end effector's pose.
KINEMATICS = {
    "ee-tf": "one world -> ee transform on /tf (and ee -> fingers)",
    "tf-chain": "a gantry robot's links: world -> base_link (static) -> six moving links -> flange -> tool0 -> ee "
                "(static), fingers on /tf",
    "joint-states": "no robot TF: /joint_states of the gantry and its fingers, with the robot's URDF (robot.urdf)",
}
URDF_FILE = f"{robot.ROBOT_NAME}.urdf"  # written beside the scene config
SDF_RESOLUTION_M = 0.00025  # the config's default contact.sdf_resolution_m
# the scene configs' masking.tactile_depth_tolerance_m [m]: the depth topics hold the exact
# indentation (to INDENTATION_STEP_M), so a pose pressed 0.05 mm deeper than measured is ruled out
DEPTH_TOLERANCE_M = 5e-5
# the scene configs' edges.gain per built-in object: the camera contour term where the part's
# outline stands clear of other edges in the simulated images (README: Camera contour term)
CONTOUR_GAIN = {"plug": 3.0, "shaft_peg": 3.0}
# the scene configs' filter settings per built-in object, where they differ from the defaults:
# the cube's sharper likelihood narrows its estimate along the end effector's x axis, which its
# misses lie along (README: The cube's likelihood temperature); conn2's side camera sees a few
# pixels of the part once it is in the receptacle, and weighs in by its mask's area under 200
# image pixels (README: Small camera masks)
FILTER_SETTINGS = {"cube": {"temperature": 0.0015}, "conn2": {"camera_full_weight_px": 200.0}}


@dataclass(frozen=True)
class SimulateOptions:
    """Everything that defines a simulated log besides the seed and the object."""

    episode: EpisodeOptions = field(default_factory=EpisodeOptions)
    width: int = 640
    height: int = 480
    noise_std: float = 2.0  # camera read noise [DN]
    exposure_jitter: float = 0.0  # std of the per-frame log exposure (0: constant lighting)
    low_contrast: bool = False  # object painted like the gripper (the paper's peg case)
    object_rgb: tuple[float, float, float] | None = None  # paint the object this colour (0-1)
    distortion: tuple[float, ...] | None = None  # camera lens distortion, plumb_bob k1 k2 p1 p2 k3
    occluders: int = 0  # extra cables in front of the object
    image_format: str = "jpeg"  # cameras: jpeg | png | raw
    tactile_format: str = "jpeg"  # tactile images: jpeg | png | raw
    jpeg_quality: int = 90
    gel_distance_m: float = 0.025
    tactile_noise_std: float = 1.5
    compression: str = "zstd"
    kinematics: str = "ee-tf"  # how the log gives the end effector: a key of KINEMATICS
    timing: SensorTiming = field(default_factory=SensorTiming)  # sensor rates, dropped images, capture jitter
    mask_topics: bool = False  # record each camera's true object mask, as an external segmenter would
    mask_format: str = "raw"  # recorded masks: raw (sensor_msgs/Image mono8) | png (CompressedImage)
    mask_error_px: int = 0  # degrade the recorded masks: grow or shrink each by up to this many pixels
    shadows: bool = False  # the key light casts shadows; dim ambient light leaves faces dark
    glossy: bool = False  # the object is polished plastic (specular highlights)
    clutter: bool = False  # textured table and board, boxes and cylinders around the board
    light_change: float = 0.0  # how much the key light turns and the lights dim or brighten per frame


# ``--scene hard``: every harder-image option on (and the exposure changing per frame).
HARD_SCENE = {"shadows": True, "glossy": True, "clutter": True, "light_change": 0.3, "exposure_jitter": 0.1}
SCENES = ("default", "hard")


def scene_options(options: SimulateOptions, scene: str) -> SimulateOptions:
    """``options`` with the camera scene ``scene`` (one of SCENES) applied."""
    if scene not in SCENES:
        raise MvtopError(f"scene must be one of {', '.join(SCENES)}, got {scene!r}")
    return replace(options, **HARD_SCENE) if scene == "hard" else options


@dataclass(frozen=True)
class SimulationSummary:
    path: Path
    frames: int
    contact_frames: int
    bytes: int


def _material(rgba, metallic=0.0, roughness=0.7) -> Material:
    return Material(tuple(float(c) for c in rgba[:3]), metallic, roughness)


def _cable(rng: np.random.Generator) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A 3 mm cable hanging from above the object, in the object frame."""
    length = rng.uniform(0.05, 0.09)
    cyl = trimesh.creation.cylinder(radius=0.0015, height=length, sections=16)
    tilt = se3.make_pose(
        se3.rotvec_to_matrix(np.array([rng.uniform(0.3, 0.8), rng.uniform(-0.8, 0.8), 0.0])), np.zeros(3)
    )
    offset = se3.make_pose(np.eye(3), [rng.uniform(-0.01, 0.01), rng.uniform(-0.02, -0.012), 0.02 + length / 2])
    return cyl, offset @ tilt


@dataclass
class SensorRig:
    """The simulated sensors of one scene: the two cameras and their renderer, the tactile
    camera and its renderer, the gel backgrounds, the occluding cables and the lighting; what
    ``write_images`` renders a frame with. ``close`` releases the renderers."""

    cameras: list
    cam_renderer: CameraSceneRenderer
    tac_renderer: CameraSceneRenderer
    tac_camera: object
    T_finger_tac: np.ndarray
    mm_per_px: float
    backgrounds: dict
    cables: list
    key_dir: np.ndarray
    lens: tuple | None

    @classmethod
    def build(cls, spec, T_world_rec: np.ndarray, options: SimulateOptions, scene_rng: np.random.Generator,
              tac_rng: np.random.Generator, clutter_rng: np.random.Generator | None = None) -> SensorRig:
        """The rig of ``spec``'s scene with its receptacle at ``T_world_rec``; draws the cables
        from ``scene_rng``, the gel backgrounds from ``tac_rng`` and, with ``options.clutter``,
        the clutter around the board from ``clutter_rng``."""
        target = T_world_rec[:3, 3] + np.array([0.0, 0.0, 0.012])
        cameras = camera_placements(target, options.width, options.height)
        lens = None
        if options.distortion is not None:
            D = np.asarray(options.distortion, dtype=np.float64)
            cameras = [replace(c, camera=replace(c.camera, distortion_model="plumb_bob", distortion=D))
                       for c in cameras]
            lens = distortion_maps(cameras[0].camera)
        fingers = grip.gripper_meshes()
        finger_mat = _material(grip.FINGER_COLOR_RGBA, metallic=0.6, roughness=0.45)
        obj_mat = finger_mat if options.low_contrast else _material(spec.color_rgba, spec.metallic, spec.roughness)
        if options.object_rgb is not None:
            obj_mat = Material(tuple(float(c) for c in options.object_rgb), 0.0, 0.8)
        if options.glossy:
            obj_mat = hard.glossy(obj_mat)
        parts: dict[str, tuple[trimesh.Trimesh, Material]] = {
            "table": (table_mesh(), Material((0.36, 0.30, 0.24), 0.0, 0.9)),
            "board": (board_mesh(), Material((0.12, 0.30, 0.16), 0.0, 0.6)),
            "receptacle": (spec.receptacle_mesh, _material(spec.receptacle_color_rgba, 0.0, 0.5)),
            "finger_left": (fingers["left"], finger_mat),
            "finger_right": (fingers["right"], finger_mat),
            "object": (spec.mesh, obj_mat),
        }
        cables = [_cable(scene_rng) for _ in range(options.occluders)]
        for i, (mesh, _) in enumerate(cables):
            parts[f"cable{i}"] = (mesh, Material((0.08, 0.08, 0.09), 0.0, 0.5))
        if options.clutter:
            if clutter_rng is None:
                raise ValueError("a cluttered scene needs clutter_rng")
            parts.update(hard.cluttered_parts(clutter_rng))
        if options.shadows:
            cam_renderer = CameraSceneRenderer(parts, options.width, options.height, shadows=True,
                                               ambient=hard.HARD_AMBIENT)
        else:
            cam_renderer = CameraSceneRenderer(parts, options.width, options.height)
        cam_renderer.set_pose("receptacle", T_world_rec)
        tac_camera = grip.tactile_camera(options.gel_distance_m)
        tac_renderer = CameraSceneRenderer({"object": (spec.mesh, obj_mat)}, tac_camera.width, tac_camera.height)
        T_finger_tac = grip.T_finger_tactile_optical(options.gel_distance_m)
        mm_per_px = 1000.0 * options.gel_distance_m / tac_camera.fx
        backgrounds = {side: make_background(tac_camera.height, tac_camera.width, tac_rng) for side in TACTILE_SIDES}

        key_dir = se3.make_pose(se3.rotvec_to_matrix(np.array([np.radians(-50.0), np.radians(25.0), 0.0])), np.zeros(3))
        return cls(cameras, cam_renderer, tac_renderer, tac_camera, T_finger_tac, mm_per_px, backgrounds, cables,
                   key_dir, lens)

    def static_transforms(self, kinematics: str) -> list[tuple[str, str, np.ndarray]]:
        """The /tf_static transforms of a log written with ``kinematics`` (see KINEMATICS)."""
        static = [(("world", f"{c.name}_optical", c.T_world_camera)) for c in self.cameras]
        if kinematics == "tf-chain":
            static += robot.static_transforms()
        elif kinematics == "joint-states":  # the URDF carries everything past base_link
            static += robot.static_transforms()[:1]
        if kinematics != "joint-states":
            static += [(f"finger_{s}", f"tactile_{s}_optical", self.T_finger_tac) for s in TACTILE_SIDES]
        return static

    def close(self) -> None:
        self.cam_renderer.close()
        self.tac_renderer.close()


def simulate(
    object_name: str,
    seed: int,
    out: Path,
    options: SimulateOptions = SimulateOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> SimulationSummary:
    """Simulate one episode of ``object_name`` (a built-in object's name, an object file's path
    or an ObjectSpec) with ``seed`` and write the log to ``out``."""
    if options.image_format not in ("jpeg", "png", "raw") or options.tactile_format not in ("jpeg", "png", "raw"):
        raise MvtopError(
            f"image formats must be jpeg, png or raw, got {options.image_format!r}/{options.tactile_format!r}"
        )
    if options.mask_format not in ("raw", "png"):
        raise MvtopError(f"mask format must be raw or png, got {options.mask_format!r}")
    if options.kinematics not in KINEMATICS:
        raise MvtopError(f"kinematics must be one of {', '.join(KINEMATICS)}, got {options.kinematics!r}")
    spec = resolve_object(object_name)
    rng = np.random.default_rng(seed)
    ep_rng, cam_rng, tac_rng, scene_rng = (np.random.default_rng(s) for s in rng.integers(0, 2**63, size=4))
    timing_rng = np.random.default_rng(rng.integers(0, 2**63))  # drawn after the others: they stay as they were
    mask_rng, light_rng, clutter_rng = (np.random.default_rng(s) for s in rng.integers(0, 2**63, size=3))  # likewise

    T_world_rec = receptacle_pose(spec.receptacle_mesh)
    collider = Collider(spec.mesh, [(spec.receptacle_mesh, T_world_rec), (board_mesh(), np.eye(4))])
    states = plan_episode(T_world_rec, spec.insertion_depth_m, spec.grasp, spec.mesh, collider, options.episode, ep_rng,
                          spec.grasp_squeeze)
    sensors = [("front", "camera"), ("side", "camera")] + [(s, "tactile") for s in TACTILE_SIDES]
    try:
        schedule = capture_schedule([s.stamp_ns for s in states], sensors, options.timing, timing_rng)
    except ValueError as err:
        raise MvtopError(f"sensor timing: {err}") from None
    robot_states = _robot_samples(states, options.timing)

    rig = SensorRig.build(spec, T_world_rec, options, scene_rng, tac_rng, clutter_rng)
    t0 = robot_states[0].stamp_ns
    try:
        with LogWriter(out, compression=options.compression) as log:
            log.write_tf(rig.static_transforms(options.kinematics), t0, static=True)
            for st in (s for s in robot_states if s.stamp_ns < states[0].stamp_ns):  # held before the frames
                write_robot(log, st, options.kinematics)
            for k, st in enumerate(states):
                write_robot(log, st, options.kinematics)
                write_images(log, st, schedule[k], states, rig, options, cam_rng, tac_rng, mask_rng, light_rng)
                if progress is not None:
                    progress(k + 1, len(states))
            for st in (s for s in robot_states if s.stamp_ns > states[-1].stamp_ns):  # held after them
                write_robot(log, st, options.kinematics)
    finally:
        rig.close()
    return SimulationSummary(Path(out), len(states), sum(s.contact for s in states), os.path.getsize(out))


def _robot_samples(states: list[EpisodeState], timing: SensorTiming) -> list[EpisodeState]:
    """The states the robot's streams (TF or joint states, contact, wrench, ground truth)
    publish: one per frame; with capture jitter also one a period before the first frame and
    one after the last (the robot at rest there), so every capture lies within the recorded
    motion, as with a recorder started before the sensors and stopped after them."""
    if timing.jitter_s == 0.0 or len(states) < 2:
        return list(states)
    dt = states[1].stamp_ns - states[0].stamp_ns
    return ([replace(states[0], stamp_ns=states[0].stamp_ns - dt)] + list(states)
            + [replace(states[-1], stamp_ns=states[-1].stamp_ns + dt)])


def write_robot(log, st: EpisodeState, kinematics: str) -> None:
    """The robot's streams at ``st``: the end effector as ``kinematics`` says (see
    KINEMATICS), joint states, contact, wrench and the ground-truth object pose."""
    t = st.stamp_ns
    T_ee_fingers = grip.finger_poses(st.finger_opening_m)
    fingers = [("ee", f"finger_{s}", T_ee_fingers[s]) for s in TACTILE_SIDES]
    finger_q = robot.finger_joint_values(st.pad_left_y_m, st.pad_right_y_m)
    if kinematics == "ee-tf":
        log.write_tf([("world", "ee", st.T_world_ee)] + fingers, t)
        log.write_joint_state("/joint_states", FINGER_JOINTS, finger_q, t)
    else:
        q = robot.inverse_kinematics(st.T_world_ee)
        if kinematics == "tf-chain":
            log.write_tf(robot.arm_transforms(q) + fingers, t)
        log.write_joint_state("/joint_states", robot.ARM_JOINTS + FINGER_JOINTS, [float(v) for v in q] + finger_q, t)
    log.write_bool("/contact", bool(st.contact), t)
    log.write_wrench("/wrench", [0.0, 0.0, st.press_force_n], [0.0, 0.0, 0.0], t, "ee")
    log.write_pose("/ground_truth/object_pose", st.T_world_object, t, "world")


def write_images(log, st: EpisodeState, capture: dict[str, int | None], states: list[EpisodeState], rig: SensorRig,
                 options: SimulateOptions, cam_rng, tac_rng, mask_rng=None, light_rng=None) -> None:
    """The images of frame ``st`` rendered with ``rig``: each sensor in ``capture`` renders the
    scene at its capture time (the frame's own state when that is the frame's time, else
    interpolated in ``states``) and stamps it with that time; sensors whose capture is None
    publish nothing. With ``options.mask_topics`` each camera image also gets its object mask
    (``mask_rng`` degrades it); ``light_rng`` changes the lights per frame
    (``options.light_change``)."""
    cameras, cam_renderer, tac_renderer, tac_camera = rig.cameras, rig.cam_renderer, rig.tac_renderer, rig.tac_camera
    T_finger_tac, mm_per_px, backgrounds, cables, key_dir, lens = (
        rig.T_finger_tac, rig.mm_per_px, rig.backgrounds, rig.cables, rig.key_dir, rig.lens)

    def at(t: int) -> EpisodeState:
        return st if t == st.stamp_ns else state_at(states, t)

    exposure = float(np.exp(cam_rng.normal(0.0, options.exposure_jitter))) if options.exposure_jitter > 0 else 1.0
    fill_at = st.T_world_object[:3, 3] + np.array([-0.15, -0.25, 0.35])
    if options.shadows or options.light_change > 0:
        key, fill = (hard.HARD_KEY_INTENSITY, hard.HARD_FILL_INTENSITY) if options.shadows else (3.0, 1.2)
        cam_renderer.set_lights(*_frame_lights(light_rng, key_dir, fill_at, options.light_change, key, fill))
    else:
        cam_renderer.set_lights(key_dir, fill_at, 3.0, 1.2)
    photo = PhotometricOptions(exposure=exposure, noise_std=options.noise_std)
    for cam in cameras:
        t = capture[cam.name]
        if t is None:
            continue
        s = at(t)
        T_world_obj = s.T_world_object
        T_ee_fingers = grip.finger_poses(s.finger_opening_m)
        cam_renderer.set_pose("object", T_world_obj)
        for side in TACTILE_SIDES:
            cam_renderer.set_pose(f"finger_{side}", s.T_world_ee @ T_ee_fingers[side])
        for i, (_, T_obj_cable) in enumerate(cables):
            cam_renderer.set_pose(f"cable{i}", T_world_obj @ T_obj_cable)
        pinhole = replace(cam.camera, distortion=np.zeros(5))
        linear, _ = cam_renderer.render(pinhole, cam.T_world_camera)
        if lens is not None:  # the pinhole render seen through the lens
            import cv2

            linear = cv2.remap(linear, lens[0], lens[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        rgb = apply_camera_effects(linear, photo, cam_rng)
        _write_rgb(
            log, f"/cameras/{cam.name}/image", rgb, t, f"{cam.name}_optical", options.image_format, options.jpeg_quality
        )
        if options.mask_topics:
            visible = cam_renderer.visible_mask(pinhole, cam.T_world_camera, only="object")
            mask = object_mask_image(visible, lens, options.mask_error_px, mask_rng)
            topic = f"/cameras/{cam.name}/mask" + ("/compressed" if options.mask_format == "png" else "")
            log.write_mask(topic, mask, t, f"{cam.name}_optical", fmt=options.mask_format)
        log.write_camera_info(f"/cameras/{cam.name}/camera_info", cam.camera, t, f"{cam.name}_optical")

    for side in TACTILE_SIDES:
        t = capture[side]
        if t is None:
            continue
        s = at(t)
        T_world_tac = s.T_world_ee @ grip.finger_poses(s.finger_opening_m)[side] @ T_finger_tac
        tac_renderer.set_pose("object", s.T_world_object)
        depth = tac_renderer.render_depth_only(tac_camera, T_world_tac, only="object")
        indentation = indentation_from_depth(depth, options.gel_distance_m)
        img = render_tactile_image(
            indentation, mm_per_px, backgrounds[side], tac_rng, noise_std=options.tactile_noise_std
        )
        frame_id = f"tactile_{side}_optical"
        _write_rgb(log, f"/tactile/{side}/image", img, t, frame_id, options.tactile_format, options.jpeg_quality)
        log.write_depth(f"/tactile/{side}/depth", indentation, t, frame_id)
        log.write_camera_info(f"/tactile/{side}/camera_info", tac_camera, t, frame_id)


def _frame_lights(rng, key_dir: np.ndarray, fill_at: np.ndarray, change: float, key: float, fill: float):
    T_key, key, fill = hard.frame_lights(rng, key_dir, change, key, fill)
    return T_key, fill_at, key, fill


def object_mask_image(visible: np.ndarray, lens=None, error_px: int = 0, rng=None) -> np.ndarray:
    """What a segmenter would publish for one camera image: (H, W) uint8, 255 on the object's
    visible pixels (``visible`` of the pinhole render, seen through ``lens`` when the camera
    has distortion), grown or shrunk by a random 0 to ``error_px`` pixels (``rng``)."""
    import cv2

    mask = visible.astype(np.uint8) * 255
    if lens is not None:
        mask = cv2.remap(mask, lens[0], lens[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
    if error_px > 0:
        k = int(rng.integers(-error_px, error_px + 1))
        if k != 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(k) + 1, 2 * abs(k) + 1))
            mask = cv2.dilate(mask, kernel) if k > 0 else cv2.erode(mask, kernel)
    return mask


def distortion_maps(camera) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (H, W) float32 that turn a pinhole image of ``camera`` into the image its
    lens distortion makes: for each distorted pixel, where its ray lands in the pinhole image."""
    import cv2

    H, W = camera.height, camera.width
    uv = np.stack(np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)), -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(uv, camera.K, np.asarray(camera.distortion, dtype=np.float64), P=camera.K)
    und = und.reshape(H, W, 2).astype(np.float32)
    return und[..., 0], und[..., 1]


def indentation_from_depth(depth_m: np.ndarray, gel_distance_m: float, gel_thickness_m: float = 0.004) -> np.ndarray:
    """Gel indentation (H, W) float32 [m] from the object's depth seen by the tactile camera:
    how far the object surface reaches past the undeformed gel plane (0 where it does not),
    on a 1 um grid (far below what a gel resolves; it makes the depth topic compress 15x)."""
    ind = np.where(depth_m > 0, gel_distance_m - depth_m, 0.0)
    ind = np.clip(ind, 0.0, gel_thickness_m)
    return (np.round(ind / INDENTATION_STEP_M) * INDENTATION_STEP_M).astype(np.float32)


def _write_rgb(log, base_topic: str, rgb: np.ndarray, t: int, frame_id: str, fmt: str, quality: int) -> None:
    if fmt == "raw":
        log.write_image(base_topic, rgb, t, frame_id, encoding="rgb8")
    else:
        log.write_compressed_image(f"{base_topic}/compressed", rgb, t, frame_id, fmt=fmt, jpeg_quality=quality)


def scene_config(object_name: str, mesh_dir: str = "meshes", gel_distance_m: float | None = None,
                 options: SimulateOptions | None = None) -> dict:
    """The YAML config (as plain data) that describes the simulated scene of ``object_name`` so
    that ``mvtop estimate`` runs on its logs; mesh paths are relative to the config file.

    ``options`` (default: SimulateOptions()) are those the logs were simulated with: they
    decide the image topics (compressed or raw), the gel distance [m] (unless
    ``gel_distance_m`` is given) and, for ``kinematics="joint-states"``, ``robot.urdf``
    (``URDF_FILE`` beside the config, see :func:`write_scene_config`). The simulated pads'
    depth is exact, so the config sets ``masking.tactile_depth_tolerance_m`` (``DEPTH_TOLERANCE_M``);
    for the objects of ``CONTOUR_GAIN`` it turns the camera contour term on (``edges.gain``), for
    those of ``FILTER_SETTINGS`` it sets their ``filter`` keys."""
    options = options or SimulateOptions()
    if gel_distance_m is None:
        gel_distance_m = options.gel_distance_m
    suffix = {fmt: "" if fmt == "raw" else "/compressed" for fmt in ("jpeg", "png", "raw")}
    spec = resolve_object(object_name)
    object_name = spec.name
    T_world_rec = receptacle_pose(spec.receptacle_mesh)
    from ..config import PoseSpec

    def pose(T: np.ndarray) -> dict:
        p = PoseSpec.from_matrix(T)
        return {"xyz_m": [round(v, 9) for v in p.xyz_m], "rpy_deg": [round(v, 9) for v in p.rpy_deg]}

    sym = []
    for S in spec.symmetry[1:]:
        sym.append(pose(S))
    cameras = [
        {"name": n, "image_topic": f"/cameras/{n}/image{suffix[options.image_format]}",
         "info_topic": f"/cameras/{n}/camera_info", "frame": f"{n}_optical"}
        for n in ("front", "side")
    ]
    if options.mask_topics:
        for c in cameras:
            c["mask_topic"] = f"/cameras/{c['name']}/mask" + ("/compressed" if options.mask_format == "png" else "")
    tactile = [
        {"name": s, "image_topic": f"/tactile/{s}/image{suffix[options.tactile_format]}",
         "info_topic": f"/tactile/{s}/camera_info", "depth_topic": f"/tactile/{s}/depth",
         "frame": f"tactile_{s}_optical", "gel_distance_m": gel_distance_m}
        for s in TACTILE_SIDES
    ]
    cfg = {
        "object": {
            "name": object_name,
            "mesh": f"{mesh_dir}/{object_name}.obj",
            "units": "m",
            "clearance_m": float(spec.clearance_m),
            "insertion_depth_m": float(spec.insertion_depth_m),
            "symmetries": sym,
            **_extra_object_keys(spec, mesh_dir),
        },
        "environment": [
            {"name": "receptacle", "mesh": f"{mesh_dir}/{object_name}_receptacle.obj", "frame": "world",
             "pose": pose(T_world_rec)},
            {"name": "board", "mesh": f"{mesh_dir}/board.obj", "frame": "world"},
            {"name": "finger_left", "mesh": f"{mesh_dir}/finger.obj", "frame": "finger_left", "collide": False},
            {"name": "finger_right", "mesh": f"{mesh_dir}/finger.obj", "frame": "finger_right", "collide": False},
        ],
        "sensors": {"cameras": cameras, "tactile": tactile},
        "grasp_prior": {
            "pose": pose(spec.grasp), "distribution": "uniform", "translation_m": 0.003, "rotation_deg": 10.0
        },
    }
    cfg["masking"] = {"tactile_depth_tolerance_m": DEPTH_TOLERANCE_M}
    if options.mask_topics:
        cfg["masking"]["camera"] = {"backend": "topic"}
    if options.kinematics == "joint-states":
        cfg["robot"] = {"urdf": URDF_FILE}
    if object_name in CONTOUR_GAIN:
        cfg["edges"] = {"gain": CONTOUR_GAIN[object_name]}
    if object_name in FILTER_SETTINGS:
        cfg["filter"] = dict(FILTER_SETTINGS[object_name])
    if spec.clearance_m < SDF_RESOLUTION_M:  # contact/grid.py: the grid must resolve the clearance
        cfg["contact"] = {"sdf_resolution_m": round(spec.clearance_m / 2.0, 9)}
    return cfg


def export_scene_meshes(out_dir: Path, objects: list[str] | None = None) -> list[Path]:
    """Write the meshes the scene configs reference (object, receptacle, finger, board) as OBJ
    files into ``out_dir``; returns the paths written."""
    from ..io.meshes import write_obj
    from ..sim.objects import list_objects

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    meshes = {}
    for ref in objects or list_objects():
        spec = resolve_object(ref)
        meshes[spec.name] = spec.mesh
        meshes[f"{spec.name}_receptacle"] = spec.receptacle_mesh
        if spec.render_mesh is not None:
            meshes[f"{spec.name}_render"] = spec.render_mesh
    meshes["finger"] = grip.gripper_meshes()["left"]
    meshes["board"] = board_mesh()
    return [write_obj(mesh, out_dir / f"{name}.obj", name) for name, mesh in meshes.items()]


def _extra_object_keys(spec, mesh_dir: str) -> dict:
    """The config's object keys beyond the built-in objects' (written only when the part has them)."""
    out = {}
    if spec.continuous_symmetry is not None:
        c = spec.continuous_symmetry
        out["continuous_symmetry"] = {"axis": [float(v) for v in c.axis], "point_m": [float(v) for v in c.point_m]}
    if spec.render_mesh is not None:
        out["render_mesh"] = f"{mesh_dir}/{spec.name}_render.obj"
    if spec.directional_clearance is not None:
        d = spec.directional_clearance
        out["directional_clearance"] = {"x_m": [float(v) for v in d.x_m], "y_m": [float(v) for v in d.y_m]}
    return out


def write_scene_config(object_name: str, path: Path, options: SimulateOptions | None = None) -> Path:
    """Write the scene config of ``object_name`` for logs simulated with ``options`` to
    ``path``, its meshes to ``meshes/`` beside it and, for ``kinematics="joint-states"``, the
    robot's URDF (``URDF_FILE``) beside it."""
    import yaml

    from ..io.atomic import atomic_output

    options = options or SimulateOptions()
    path = Path(path)
    export_scene_meshes(path.parent / "meshes", [object_name])
    if options.kinematics == "joint-states":
        with atomic_output(path.parent / URDF_FILE) as fh:
            fh.write(robot.urdf_text(options.gel_distance_m).encode())
    how = f"--object {object_name}" if isinstance(object_name, str) and not object_name.endswith((".yaml", ".yml")) \
        else f"--object-file, object {resolve_object(object_name).name!r}"
    text = (
        f"# mvtop config for the simulated {resolve_object(object_name).name} scene (mvtop simulate {how}).\n"
        "# Units: metres and degrees as the key names say; mesh paths are relative to this file.\n"
        + yaml.safe_dump(scene_config(object_name, options=options), sort_keys=False, default_flow_style=None)
    )
    with atomic_output(path) as fh:
        fh.write(text.encode())
    return path
