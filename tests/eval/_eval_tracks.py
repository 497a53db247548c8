"""Tiny fake estimate folders and ground-truth logs for the eval tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mvtop_cli.config import dump_config, load_config
from mvtop_cli.geometry import se3
from mvtop_cli.io.mcap_writer import LogWriter

REPO = Path(__file__).resolve().parents[2]
T0_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000
GT_TOPIC = "/ground_truth/object_pose"


def trajectory(n: int, seed: int = 0, object_name: str = "conn1") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (n,) [ns], ``T_world_object`` and ``T_world_ee`` (n, 4, 4) of an object held in
    the nominal grasp of ``configs/<object>.yaml`` while the gripper descends and turns a bit."""
    rng = np.random.default_rng(seed)
    cfg = load_config(REPO / "configs" / f"{object_name}.yaml")
    T_ee_obj = cfg.grasp_prior.pose.matrix()
    stamps = T0_NS + STEP_NS * np.arange(n, dtype=np.int64)
    down = se3.make_pose(Rotation.from_euler("x", 180, degrees=True).as_matrix(), (0, 0, 0.05))  # ee z points down
    T_world_ee = np.stack([
        se3.make_pose(Rotation.from_rotvec(rng.normal(0, 0.02, 3)).as_matrix() @ down[:3, :3],
                      (0.01 - 0.001 * i, 0.005, 0.06 - 0.003 * i))
        for i in range(n)
    ])
    return stamps, T_world_ee @ T_ee_obj, T_world_ee


def write_gt_log(path: Path, stamps: np.ndarray, T_world_object: np.ndarray | None, topic: str = GT_TOPIC) -> Path:
    """A log with the ground truth on ``topic`` (and a contact flag, so a log without truth
    still has a topic)."""
    with LogWriter(path) as w:
        for i, s in enumerate(stamps):
            w.write_bool("/contact", False, int(s))
            if T_world_object is not None:
                w.write_pose(topic, T_world_object[i], int(s), "world")
    return path


def write_track(
    folder: Path,
    object_name: str,
    stamps: np.ndarray,
    T_world_object: np.ndarray,
    T_world_ee: np.ndarray,
    std_translation_m: np.ndarray | float = 1e-4,
    std_rotation_deg: np.ndarray | float = 0.1,
    final_covariance: np.ndarray | None = None,
    particles: int = 100,
) -> Path:
    """track.csv, summary.json and config.resolved.yaml as ``mvtop estimate`` writes them."""
    folder.mkdir(parents=True, exist_ok=True)
    n = len(stamps)
    T_ee_object = se3.invert(T_world_ee) @ T_world_object
    st = np.broadcast_to(np.asarray(std_translation_m, dtype=float), (n,))
    sr = np.broadcast_to(np.asarray(std_rotation_deg, dtype=float), (n,))
    lines = ["frame,stamp_ns,x_m,y_m,z_m,qx,qy,qz,qw,ee_x_m,ee_y_m,ee_z_m,ee_qx,ee_qy,ee_qz,ee_qw,"
             "std_translation_m,std_rotation_deg,ess,contact,mask_mode,flags"]
    for i in range(n):
        vals = [*T_world_object[i, :3, 3], *se3.to_quat_xyzw(T_world_object[i]),
                *T_ee_object[i, :3, 3], *se3.to_quat_xyzw(T_ee_object[i])]
        lines.append(",".join([str(i), str(int(stamps[i]))] + [repr(float(v)) for v in vals]
                              + [repr(float(st[i])), repr(float(sr[i])), f"{0.8 * particles:.2f}", "0", "prompt", ""]))
    (folder / "track.csv").write_text("\n".join(lines) + "\n")
    if final_covariance is None:
        final_covariance = np.diag([st[-1] ** 2] * 3 + [np.radians(sr[-1]) ** 2] * 3)
    summary = {
        "log": "fake.mcap", "object": object_name, "modalities": ["vision"], "particles": particles, "seed": 0,
        "frames_processed": n, "time_per_frame_s": 0.5,
        "final": {"stamp_ns": int(stamps[-1]), "covariance_ee": np.asarray(final_covariance).tolist()},
    }
    (folder / "summary.json").write_text(json.dumps(summary, indent=2))
    cfg = load_config(REPO / "configs" / f"{object_name}.yaml")
    (folder / "config.resolved.yaml").write_text(dump_config(cfg))
    return folder
