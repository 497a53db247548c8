"""A synthetic visuo-tactile log with known motion (imported by the io tests), and the real rosbag2 logs' folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from _real_data import REAL_DATA

from mvtop_cli.geometry import se3
from mvtop_cli.geometry.camera import PinholeCamera
from mvtop_cli.io.mcap_writer import LogWriter

REAL = REAL_DATA / "rosbag2_mcap"

T0 = 1_700_000_000_000_000_000  # a realistic epoch stamp [ns]
SEC = 1_000_000_000
MS = 1_000_000


def rot(axis: str, angle: float) -> np.ndarray:
    v = {"x": [1.0, 0, 0], "y": [0, 1.0, 0], "z": [0, 0, 1.0]}[axis]
    return se3.rotvec_to_matrix(np.asarray(v) * angle)


def pose(R: np.ndarray, t) -> np.ndarray:
    return se3.make_pose(R, t)


@dataclass
class Scene:
    """Analytic ground truth of the synthetic log; ``s`` is seconds since T0.

    Chain world -> base (static) -> link (moving) -> ee (moving) -> tactile optical
    frames (static); cameras static in world. Each moving edge translates along a line
    and turns about a fixed axis at a constant rate, so per-edge linear/slerp
    interpolation is exact.
    """

    T_world_base = pose(rot("z", np.pi / 6), [0.3, -0.2, 0.1])
    T_ee_left = pose(rot("x", -np.pi / 2), [0.0, 0.012, 0.0])
    T_ee_right = pose(rot("x", np.pi / 2), [0.0, -0.012, 0.0])
    T_world_front = pose(rot("x", np.pi) @ rot("z", 0.1), [0.5, 0.0, 0.6])
    T_world_side = pose(rot("y", np.pi / 2), [0.0, 0.7, 0.3])
    T_ee_obj = pose(rot("z", 0.05), [0.0, 0.0, 0.03])

    @staticmethod
    def s(t_ns: int) -> float:
        return (t_ns - T0) / SEC

    def T_base_link(self, t_ns: int) -> np.ndarray:
        s = self.s(t_ns)
        return pose(rot("x", 0.2 * s), [0.1 + 0.05 * s, 0.0, 0.4])

    def T_link_ee(self, t_ns: int) -> np.ndarray:
        s = self.s(t_ns)
        return pose(rot("z", 0.5 * s), [0.0, 0.02 * s, 0.1])

    def T_world_ee(self, t_ns: int) -> np.ndarray:
        return self.T_world_base @ self.T_base_link(t_ns) @ self.T_link_ee(t_ns)

    def T_world_obj(self, t_ns: int) -> np.ndarray:
        s = self.s(t_ns)
        return pose(rot("y", 0.3 * s), [0.5, 0.1 * s, 0.02])

    @staticmethod
    def opening(t_ns: int) -> float:
        return 0.02 + 0.02 * Scene.s(t_ns)

    @staticmethod
    def contact(t_ns: int) -> bool:
        return Scene.s(t_ns) >= 0.5


CAMERA = PinholeCamera(width=32, height=24, K=np.array([[30.0, 0, 15.5], [0, 31.0, 11.5], [0, 0, 1.0]]))
TACTILE = PinholeCamera(
    width=20, height=16, K=np.array([[25.0, 0, 9.5], [0, 25.0, 7.5], [0, 0, 1.0]]),
    distortion_model="plumb_bob", distortion=np.array([0.01, -0.002, 0.0, 0.0, 0.0001]),
)

# Sensor stamp offsets from the frame trigger [ns] (within a 5 ms sync tolerance) and
# delivery latency (log time - stamp): tactile images arrive after the next camera frame.
OFFSETS = {"front": 0, "side": 2 * MS, "left": 1 * MS, "right": -1 * MS}
LATENCY = {"front": 5 * MS, "side": 7 * MS, "left": 120 * MS, "right": 130 * MS}
N_FRAMES = 10
MISSING = {("side", 3)}  # (sensor, k) with no image


def trigger(k: int) -> int:
    return T0 + 50 * MS + k * 100 * MS


def image_of(sensor: str, k: int, shape: tuple[int, int]) -> np.ndarray:
    seed = sum(map(ord, sensor)) * 100 + k + 1000
    return np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)


def depth_of(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0 : TACTILE.height, 0 : TACTILE.width]
    return (1e-4 * k * np.exp(-((xx - 10.0) ** 2 + (yy - 8.0) ** 2) / 20.0)).astype(np.float32)


def write_scene(path: Path, compression: str = "zstd", early_image: bool = True) -> Scene:
    """Write the synthetic scene log to ``path``; returns the analytic Scene."""
    sc = Scene()
    with LogWriter(path, compression=compression, chunk_size=64 * 1024) as w:
        w.write_tf(
            [
                ("world", "base", sc.T_world_base),
                ("ee", "tactile_left_optical", sc.T_ee_left),
                ("ee", "tactile_right_optical", sc.T_ee_right),
                ("world", "front_optical", sc.T_world_front),
                ("world", "side_optical", sc.T_world_side),
            ],
            T0,
            static=True,
        )
        events = []
        for i in range(101):  # 100 Hz for 1 s
            t = T0 + i * 10 * MS
            events.append((t, "tf", i))
        for k in range(N_FRAMES):
            for name in OFFSETS:
                if (name, k) in MISSING:
                    continue
                st = trigger(k) + OFFSETS[name]
                events.append((st + LATENCY[name], name, k))
        if early_image:  # before the first /tf sample: this frame must be skipped
            events.append((T0 - 30 * MS + LATENCY["front"], "front", -1))
        for log_t, kind, k in sorted(events, key=lambda e: (e[0], e[1])):
            if kind == "tf":
                t = log_t
                w.write_tf([("base", "link", sc.T_base_link(t)), ("link", "ee", sc.T_link_ee(t))], t)
                w.write_bool("/contact", sc.contact(t), t)
                half = sc.opening(t) / 2
                w.write_joint_state(
                    "/joint_states", ["arm_joint1", "finger_joint1", "finger_joint2"], [0.7, half, half], t
                )
                w.write_pose("/ground_truth/object_pose", sc.T_world_obj(t), t, "world")
                w.write_wrench("/wrench", [0.0, 0.0, -1.0], [0.0, 0.0, 0.0], t, "ee")
                continue
            st = (T0 - 30 * MS) if k < 0 else trigger(k) + OFFSETS[kind]
            if kind in ("front", "side"):
                rgb = image_of(kind, k, (CAMERA.height, CAMERA.width))
                if kind == "front":
                    w.write_image("/cameras/front/image", rgb, st, "front_optical", log_time_ns=log_t)
                else:
                    w.write_compressed_image(
                        "/cameras/side/image/compressed", rgb, st, "side_optical", fmt="png", log_time_ns=log_t
                    )
                w.write_camera_info(f"/cameras/{kind}/camera_info", CAMERA, st, f"{kind}_optical", log_time_ns=log_t)
            else:
                rgb = image_of(kind, k, (TACTILE.height, TACTILE.width))
                frame = f"tactile_{kind}_optical"
                w.write_image(f"/tactile/{kind}/image", rgb, st, frame, log_time_ns=log_t)
                w.write_camera_info(f"/tactile/{kind}/camera_info", TACTILE, st, frame, log_time_ns=log_t)
                if kind == "left":
                    w.write_depth("/tactile/left/depth", depth_of(k), st, frame, log_time_ns=log_t)
    return sc
