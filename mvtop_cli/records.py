"""Small typed records that carry one observation frame from the log reader to the core.

The reader turns raw ROS 2 messages into these; nothing past ``io`` sees a message.
Poses are (4, 4) float64 ``T_a_b`` arrays (see ``geometry.se3``), times int nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import se3
from .geometry.camera import PinholeCamera


@dataclass(frozen=True)
class SensorImage:
    """One image of one sensor, with what is needed to render into it.

    ``image`` is (H, W, 3) uint8 RGB (mono images are expanded to three channels);
    ``T_world_sensor`` is the sensor's optical frame (z forward) in ``world`` at
    ``stamp_ns``; ``depth`` is, for tactile sensors that publish it, the gel
    indentation (H, W) float32 [m] (0 where undeformed). ``T_world_ee`` is the end
    effector in ``world`` at this image's own ``stamp_ns`` (sensors at different rates
    take their images at other times than the frame's stamp; the held object moves
    with the end effector, so it is placed in each image with this pose); None means
    "at the frame's stamp". ``mask`` is, for cameras whose config names a ``mask_topic``, the
    object mask an external segmenter recorded for this image: (H, W) uint16 labels as
    published (0 = background), matched to the image by stamp within the sync tolerance.
    """

    sensor: str
    stamp_ns: int
    image: np.ndarray
    camera: PinholeCamera
    T_world_sensor: np.ndarray
    depth: np.ndarray | None = None
    T_world_ee: np.ndarray | None = None
    mask: np.ndarray | None = None


@dataclass(frozen=True)
class Frame:
    """One time-ordered observation frame of a log.

    ``cameras`` and ``tactile`` map the config's sensor name to its image (a sensor
    with no image in this frame is absent). ``T_world_ee`` is the end effector (tool
    centre point between the fingertips) in ``world`` at ``stamp_ns``; ``contact`` is
    the contact state at that time (None when the log has no contact signal);
    ``finger_opening_m`` the distance between the finger pads [m] when known;
    ``T_world_object_gt`` the ground-truth object pose when the log carries one.
    """

    index: int
    stamp_ns: int
    T_world_ee: np.ndarray
    cameras: dict[str, SensorImage] = field(default_factory=dict)
    tactile: dict[str, SensorImage] = field(default_factory=dict)
    contact: bool | None = None
    finger_opening_m: float | None = None
    T_world_object_gt: np.ndarray | None = None

    def image(self, sensor: str) -> SensorImage:
        """The image of ``sensor`` (a camera or a tactile sensor) in this frame."""
        return self.cameras[sensor] if sensor in self.cameras else self.tactile[sensor]

    def T_world_ee_at(self, img: SensorImage) -> np.ndarray:
        """The end effector in ``world`` (4, 4) when ``img`` was taken: the held object is
        placed in each image with the gripper pose of that image's own stamp."""
        return self.T_world_ee if img.T_world_ee is None else img.T_world_ee

    def T_sensor_object(self, sensor: str, T_ee_object: np.ndarray) -> np.ndarray:
        """Object poses (..., 4, 4) in ``sensor``'s optical frame at its image's time:
        ``T_sensor_world @ T_world_ee(image stamp) @ T_ee_object``."""
        img = self.image(sensor)
        return se3.invert(img.T_world_sensor) @ (self.T_world_ee_at(img) @ T_ee_object)
