"""Harder simulated camera scenes (``sim.hard_scene``, ``mvtop simulate --scene hard``) and the
recorded object masks of ``--mask-topics``."""

from __future__ import annotations

import numpy as np
import pytest

from mvtop_cli.geometry import se3
from mvtop_cli.io.frames import FrameReader, LogTopics, SensorTopics
from mvtop_cli.io.mcap_reader import McapLog
from mvtop_cli.pipelines.simulate import HARD_SCENE, SimulateOptions, scene_options, simulate
from mvtop_cli.sim import hard_scene as hard
from mvtop_cli.sim.episode import EpisodeOptions


def test_textured_box_has_whole_faces_facing_out():
    box = hard.textured_box((0.2, 0.1, 0.04), (0.0, 0.0, 0.5))
    assert len(box.vertices) == 24 and len(box.faces) == 12
    assert box.visual.uv.shape == (24, 2)
    outward = np.einsum("ij,ij->i", box.face_normals, box.triangles_center - [0.0, 0.0, 0.5])
    assert (outward > 0).all()
    assert np.allclose(box.bounds, [[-0.1, -0.05, 0.48], [0.1, 0.05, 0.52]])


def test_frame_lights_change_only_when_asked_and_per_seed():
    T = se3.make_pose(se3.rotvec_to_matrix(np.array([-0.8, 0.4, 0.0])), np.zeros(3))
    same = hard.frame_lights(np.random.default_rng(0), T, 0.0, 3.0, 1.2)
    assert same[0] is T and same[1:] == (3.0, 1.2)
    a = hard.frame_lights(np.random.default_rng(0), T, 0.3, 3.0, 1.2)
    b = hard.frame_lights(np.random.default_rng(0), T, 0.3, 3.0, 1.2)
    assert np.array_equal(a[0], b[0]) and a[1:] == b[1:]
    turned = np.degrees(se3.rotation_angle(a[0][:3, :3], T[:3, :3]))
    assert 0.5 < turned < 60.0 and a[1] != 3.0


def test_clutter_stands_around_the_board_not_on_the_receptacle():
    parts = hard.cluttered_parts(np.random.default_rng(3))
    items = [m for n, (m, _) in parts.items() if n.startswith("clutter")]
    assert len(items) == hard.CLUTTER_ITEMS and {"table", "board"} <= set(parts)
    for mesh in items:
        assert np.linalg.norm(mesh.bounds.mean(axis=0)[:2]) > 0.1  # off the receptacle at the origin
    assert parts["table"][1].texture.shape == (hard.TEXTURE_PX, hard.TEXTURE_PX, 3)


def _frames(path):
    sensors = [SensorTopics(c, "camera", f"/cameras/{c}/image/compressed", f"/cameras/{c}/camera_info",
                            mask_topic=f"/cameras/{c}/mask/compressed") for c in ("front", "side")]
    with McapLog(path) as log:
        return list(FrameReader(log, sensors, LogTopics()))


def _texture(img: np.ndarray, mask: np.ndarray) -> float:
    """Mean absolute Laplacian of the grey image away from the object [DN]."""
    import cv2

    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)
    far = ~cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    return float(np.abs(cv2.Laplacian(grey, cv2.CV_32F))[far].mean())


@pytest.fixture(scope="module")
def two_scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    base = SimulateOptions(episode=EpisodeOptions(frames=4), width=160, height=120, mask_topics=True,
                           mask_format="png")
    for scene in ("default", "hard"):
        simulate("cube", 2, d / f"{scene}.mcap", scene_options(base, scene))
    return d


def test_hard_scene_changes_the_camera_images_only(two_scenes):
    default, hard_frames = _frames(two_scenes / "default.mcap"), _frames(two_scenes / "hard.mcap")
    assert len(default) == len(hard_frames) == 4
    for a, b in zip(default, hard_frames):
        assert np.array_equal(a.T_world_object_gt, b.T_world_object_gt)  # the same episode
        for cam in ("front", "side"):
            ia, ib = a.cameras[cam], b.cameras[cam]
            assert ia.mask.any()
            # clutter, texture: the background is far busier
            assert _texture(ib.image, ib.mask > 0) > 1.5 * _texture(ia.image, ia.mask > 0)  # about 2x at 160x120
    # the lights change between frames in the hard scene: the object's mean brightness varies more
    def spread(frames):
        return np.std([f.cameras["front"].image[f.cameras["front"].mask > 0].mean() for f in frames])
    assert spread(hard_frames) > spread(default)


def _messages(path) -> dict[str, list[tuple[int, bytes]]]:
    from mcap.reader import make_reader

    out: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append((message.log_time, bytes(message.data)))
    return out


def test_hard_scene_leaves_every_topic_but_the_camera_images_byte_identical(two_scenes):
    # what a method without cameras (M-TOP) reads is the default scene's: its hard-scene runs are its default runs
    default, hard_log = _messages(two_scenes / "default.mcap"), _messages(two_scenes / "hard.mcap")
    assert set(default) == set(hard_log)
    images = {f"/cameras/{c}/image/compressed" for c in ("front", "side")}
    assert images <= set(default)
    for topic in sorted(set(default) - images):
        assert default[topic] == hard_log[topic], topic
    assert {"/tactile/left/image/compressed", "/contact", "/tf", "/cameras/front/mask/compressed"} <= set(default)
    for topic in images:
        assert [t for t, _ in default[topic]] == [t for t, _ in hard_log[topic]]
        assert all(a != b for (_, a), (_, b) in zip(default[topic], hard_log[topic]))


def test_recorded_masks_follow_the_visible_object(two_scenes):
    (f, *_) = _frames(two_scenes / "default.mcap")
    img = f.cameras["front"]
    assert set(np.unique(img.mask)) == {0, 255}
    area = int((img.mask > 0).sum())
    assert 50 < area < 0.2 * img.mask.size


def test_scene_names_are_checked():
    assert scene_options(SimulateOptions(), "default") == SimulateOptions()
    hard_options = scene_options(SimulateOptions(), "hard")
    assert all(getattr(hard_options, k) == v for k, v in HARD_SCENE.items())
    with pytest.raises(Exception, match="scene must be one of default, hard, got 'dark'"):
        scene_options(SimulateOptions(), "dark")
