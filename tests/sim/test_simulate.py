"""The simulator's logs agree with their own ground truth: images, tactile, contact, bytes.

Each check reads the log back through the public reader (TF, CameraInfo, ground truth topic)
and compares with an independent model: the numba mask renderer for images, python-fcl for
contact. So a frame convention that disagrees anywhere in the chain fails here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mvtop_cli.config import load_config
from mvtop_cli.contact.fcl_distance import FclDistance
from mvtop_cli.estimator.scene import OBJECT_ID, SceneModel
from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.estimate import log_topics, sensor_topics
from mvtop_cli.pipelines.simulate import SimulateOptions, simulate, write_scene_config
from mvtop_cli.render.roi import Roi
from mvtop_cli.sim.episode import CONTACT_DISTANCE_M, EpisodeOptions
from mvtop_cli.sim.objects import get_object, list_objects

MAGENTA = (1.0, 0.0, 1.0)

def _simulate(tmp: Path, name: str, seed: int = 3, frames: int = 12, **kw) -> tuple[Path, Path]:
    tmp.mkdir(parents=True, exist_ok=True)
    log = tmp / f"{name}.mcap"
    opts = SimulateOptions(episode=EpisodeOptions(frames=frames), **kw)
    simulate(name, seed, log, opts)
    cfg = write_scene_config(name, tmp / f"{name}.yaml")
    return log, cfg

@pytest.fixture(scope="module")
def magenta_cube(tmp_path_factory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp("sim")
    return _simulate(tmp, "cube", object_rgb=MAGENTA, noise_std=0.0, image_format="png", tactile_format="png")

def _frames(log: Path, cfg_path: Path):
    cfg = load_config(cfg_path)
    with McapLog(log) as mlog:
        reader = FrameReader(mlog, sensor_topics(cfg), log_topics(cfg))
        frames = list(reader)
        tf = reader.tf
    return cfg, frames, tf

def _magenta(rgb: np.ndarray) -> np.ndarray:
    """Pixels at least about half covered by the magenta object. The test is on chroma, not
    brightness, so lit and shaded faces count alike: G small against min(R, B). An edge pixel
    mixed half and half with the table or board falls near the 0.5 threshold, matching the
    renderer's pixel-centre sampling."""
    r, g, b = (rgb[..., i].astype(float) for i in range(3))
    lo = np.minimum(r, b)
    return (lo > 20) & ((lo - g) > 0.5 * lo) & (np.abs(r - b) < 0.35 * np.maximum(r, b))


@pytest.mark.parametrize("name", list_objects())
def test_camera_images_show_the_object_where_ground_truth_puts_it(tmp_path, name):
    log, cfg_path = _simulate(
        tmp_path, name, object_rgb=MAGENTA, noise_std=0.0, image_format="png", tactile_format="png"
    )
    cfg, frames, tf = _frames(log, cfg_path)
    scene = SceneModel(cfg, build_contact=False)
    inter = union = 0
    for fr in frames:
        for cam, img in fr.cameras.items():
            T = se3.invert(img.T_world_sensor) @ fr.T_world_object_gt
            occ = scene.occluders(img.T_world_sensor, lambda f, img=img: tf.lookup("world", f, img.stamp_ns))
            rendered = scene.renderer.render_masks(OBJECT_ID, T[None], img.camera, Roi.full(img.camera), occ)[0]
            seen = _magenta(img.image)
            i, u = (rendered & seen).sum(), (rendered | seen).sum()
            inter, union = inter + i, union + u
            # where the object shows a real silhouette (not a sliver between the fingers) each
            # view agrees on its own; below ~1000 px the one-pixel boundary band weighs more
            if rendered.sum() >= 1000:
                assert i / u >= 0.95, (fr.index, cam, i / u)
            elif rendered.sum() >= 200:
                assert i / u >= 0.9, (fr.index, cam, i / u)
    assert inter / union >= 0.95


@pytest.mark.parametrize("name", ["cube", "shaft_peg", "conn2"])
def test_tactile_depth_and_image_match_the_rendered_indentation(tmp_path, name):
    import cv2

    log, cfg_path = _simulate(tmp_path, name, frames=8, tactile_format="png")
    cfg, frames, tf = _frames(log, cfg_path)
    scene = SceneModel(cfg, build_contact=False)
    gel = {t.name: t.gel_distance_m for t in cfg.sensors.tactile}
    depth_ious, edge_ratios = [], []
    for fr in frames:
        for sensor, img in fr.tactile.items():
            T = se3.invert(img.T_world_sensor) @ fr.T_world_object_gt
            rendered = scene.renderer.render_masks(
                OBJECT_ID, T[None], img.camera, Roi.full(img.camera), mode="tactile",
                gel_distance_m=gel[sensor], penetration_threshold_m=2e-5,
            )[0]
            observed = img.depth > 2e-5
            assert rendered.sum() > 100  # the pads squeeze the object in every frame
            depth_ious.append((rendered & observed).sum() / (rendered | observed).sum())
            if observed.mean() > 0.98 or observed.mean() < 0.02:
                continue  # a pad pressed flat all over shows no contact edge
            # the image changes where the indentation does: at the contact boundary
            grad = sum(np.abs(cv2.Sobel(img.image[..., c].astype(np.float32), cv2.CV_32F, 1, 0))
                       + np.abs(cv2.Sobel(img.image[..., c].astype(np.float32), cv2.CV_32F, 0, 1)) for c in range(3))
            m = observed.astype(np.uint8)
            k = np.ones((7, 7), np.uint8)
            edge = (cv2.dilate(m, k) - cv2.erode(m, k)).astype(bool)
            far = ~cv2.dilate(edge.astype(np.uint8), np.ones((21, 21), np.uint8)).astype(bool)
            edge_ratios.append(grad[edge].mean() / grad[far].mean())
    assert min(depth_ious) >= 0.97, depth_ious
    if name != "cube":  # the cube's faces cover both pads whole
        assert edge_ratios and min(edge_ratios) > 3.0, edge_ratios


def test_contact_flag_is_true_exactly_when_the_object_touches(tmp_path):
    log, cfg_path = _simulate(tmp_path, "shaft_peg", seed=5, frames=14)
    cfg, frames, _ = _frames(log, cfg_path)
    spec = get_object("shaft_peg")
    env = [p for p in cfg.environment if p.collide and p.frame == "world"]
    from mvtop_cli.io.meshes import load_mesh

    meshes = [load_mesh(p.mesh) for p in env]
    poses = np.stack([p.pose.matrix() for p in env])
    fcl_dist = FclDistance(spec.mesh, meshes, poses)
    d = fcl_dist.distance(np.stack([f.T_world_object_gt for f in frames]))
    contact = np.array([f.contact for f in frames])
    assert contact.any() and not contact.all()
    np.testing.assert_array_equal(contact, d < CONTACT_DISTANCE_M)
    # touching means touching, not hovering: contact frames sit within a micrometre
    assert np.all(d[contact] < 1e-6)
    # and nothing ever penetrates: the SDF of the environment is never negative
    scene = SceneModel(cfg)
    phi = scene.phi(np.stack([f.T_world_object_gt for f in frames]))
    assert phi.min() > -scene.sdf.env_sdf.spacing_m

def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path):
    opts = dict(frames=6, image_format="jpeg", tactile_format="png")
    a, _ = _simulate(tmp_path / "a", "conn1", seed=11, **opts)
    b, _ = _simulate(tmp_path / "b", "conn1", seed=11, **opts)
    c, _ = _simulate(tmp_path / "c", "conn1", seed=12, **opts)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()


def test_cameras_with_lens_distortion_are_undistorted_back_to_the_pinhole_images(tmp_path):
    """The simulator images through a distorting lens and records it in CameraInfo; the
    reader undistorts, which gives back the pinhole camera's images (and the pinhole render
    at the ground truth matches them)."""
    from mvtop_cli.io.images import decode_image

    D = (-0.3, 0.1, 0.001, -0.001, 0.0)
    opts = dict(object_rgb=MAGENTA, noise_std=0.0, image_format="png", frames=4)
    log, cfg_path = _simulate(tmp_path / "lens", "plug", distortion=D, **opts)
    plain, _ = _simulate(tmp_path / "pinhole", "plug", **opts)
    with McapLog(log) as mlog:
        info = next(mlog.messages("/cameras/front/camera_info")).msg
        raw = [decode_image(m.msg, m.topic) for m in mlog.messages("/cameras/front/image/compressed")]
    np.testing.assert_allclose(info.d, D)
    cfg, frames, tf = _frames(log, cfg_path)
    _, pinhole_frames, _ = _frames(plain, cfg_path)
    inner = (slice(40, 440), slice(50, 590))  # undistortion leaves the image corners empty
    for fr, ref, distorted in zip(frames, pinhole_frames, raw):
        img = fr.cameras["front"]
        assert not img.camera.has_distortion  # the reader hands out pinhole images
        pinhole = ref.cameras["front"].image.astype(float)
        err_undistorted = np.abs(img.image.astype(float) - pinhole)[inner].mean()
        err_distorted = np.abs(distorted.astype(float) - pinhole)[inner].mean()
        assert err_undistorted < 1.5 and err_distorted > 4 * err_undistorted, (err_undistorted, err_distorted)
    scene = SceneModel(cfg, build_contact=False)
    inter = union = 0
    for fr in frames:
        for img in fr.cameras.values():
            T = se3.invert(img.T_world_sensor) @ fr.T_world_object_gt
            occ = scene.occluders(img.T_world_sensor, lambda f, img=img: tf.lookup("world", f, img.stamp_ns))
            rendered = scene.renderer.render_masks(OBJECT_ID, T[None], img.camera, Roi.full(img.camera), occ)[0]
            seen = _magenta(img.image)
            inter, union = inter + (rendered & seen).sum(), union + (rendered | seen).sum()
    assert inter / union >= 0.95
