"""Forward kinematics from a URDF (through yourdfpy): link poses from joint positions.

Used when a log records joint states but not the end effector's TF: every link of the robot
becomes a moving TF edge from the URDF's root link, so the rest of mvtop looks up ``ee``, the
fingers and the tactile sensors as if the robot had published them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import se3


class UrdfKinematics:
    """A robot model: ``link_poses(names, positions)`` gives ``T_root_link`` of every link."""

    def __init__(self, path: str | Path):
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: URDF file not found")
        try:
            import yourdfpy
        except ImportError as err:  # pragma: no cover - a dependency
            raise ConfigError(f"reading {path} needs yourdfpy (pip install yourdfpy): {err}") from err
        try:
            self.robot = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False,
                                            load_collision_meshes=False)
        except Exception as err:  # yourdfpy raises many types for malformed files
            raise ConfigError(f"{path}: cannot read the URDF ({type(err).__name__}: {err})") from err
        self.path = path
        self.root = str(self.robot.base_link)
        self.links = [str(name) for name in self.robot.link_map if name != self.root]
        self.joints = set(str(j) for j in self.robot.actuated_joint_names)

    def link_poses(self, names: list[str], positions: list[float]) -> dict[str, np.ndarray]:
        """``T_root_link`` (4, 4) of every link for the joint positions given by name [m or rad];
        joints not named keep their last value (initially zero)."""
        cfg = {n: float(p) for n, p in zip(names, positions) if n in self.joints}
        if cfg:
            self.robot.update_cfg(cfg)
        return {link: np.asarray(self.robot.get_transform(link, self.root), dtype=np.float64) for link in self.links}

    def add_to_tf(
        self, tf, stamps_ns: list[int], names: list[list[str]], positions: list[list[float]], skip: set[str]
    ) -> None:
        """Add each link (but those in ``skip``, already in the log's TF) as a dynamic edge from
        the root link to ``tf`` (a TfBuffer), one sample per joint-state message."""
        for t, n, p in zip(stamps_ns, names, positions):
            for link, T in self.link_poses(n, p).items():
                if link in skip:
                    continue
                tf.add_dynamic(self.root, link, t, T[:3, 3], se3.to_quat_xyzw(T))
