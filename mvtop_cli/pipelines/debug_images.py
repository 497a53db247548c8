"""``mvtop estimate --debug-images``: each sensor's observed and rendered masks as image topics in track.mcap.

Per frame and per sensor with an observed mask, ``frame_masks`` keeps what the likelihood
compared (``estimator.likelihood``): the observed mask cropped to the sensor's ROI window
(``estimator.observation.Observation``) and the mask rendered in that window at the
frame's estimate (``Likelihood.rendered_masks``), both bit-packed, with the ROI, the
sensor's intrinsics and its pose in ``world``. They are kept in the checkpoint journal with
the frame's estimate (``FrameEstimate.debug_masks``; at most 2 x 128 x 128 / 8 = 4 KiB per
sensor and frame with the default window bounds), never in memory, so long logs
cost disk, not RAM, and a resumed run still has the images of the frames done before.

``write_debug_images`` then writes, at each frame's stamp and in the sensor's TF frame:

- ``/mvtop/debug/<sensor>/observed`` and ``/mvtop/debug/<sensor>/rendered``: sensor_msgs/Image
  ``mono8`` of the sensor's full image size, 255 on the mask and 0 elsewhere. The ROI window
  is pasted back at its place (``Roi.paste``: each ROI pixel fills the ``k x k`` image pixels
  it stands for when the ROI is downsampled ``k``-fold); pixels outside the window are 0
  (a tactile mask can reach past its window, which covers only the part of the image the object
  can touch: that part of the observed mask enters the IoU as an area and is not drawn). The
  IoU of the two images, with that area added to the union, is the IoU the sensor scored at
  the estimate;
- ``/mvtop/debug/<sensor>/camera_info``: the sensor's intrinsics, so an image panel can draw
  the 3D scene (the CAD model at the estimate) over the masks;
- ``/tf``: ``world -> <sensor frame>`` (the sensor's pose when its image was taken), so every
  image's frame connects to ``world`` within track.mcap.

A frame writes one record per sensor observed in it; sensors at different rates write
images only in the frames that hold one of theirs.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..estimator import Estimator, FrameEstimate
from ..geometry.camera import PinholeCamera
from ..io.mcap_writer import LogWriter
from ..records import Frame
from ..render.iou import soft_observed
from ..render.roi import Roi

TOPIC_PREFIX = "/mvtop/debug"
KINDS = ("observed", "rendered")


@dataclass(frozen=True)
class SensorMasks:
    """One sensor's masks in one frame. ``observed`` and ``rendered``: the ROI masks
    (``roi.shape``) packed with ``np.packbits``, or, for soft camera evidence (``soft``), the
    observed per-pixel object probability in 255 levels (uint8, one byte a pixel); ``camera`` the
    full image's intrinsics, ``T_world_sensor`` (4, 4) the optical frame ``frame_id`` in ``world``
    at the image's stamp."""

    sensor: str
    frame_id: str
    tactile: bool
    roi: Roi
    camera: PinholeCamera
    T_world_sensor: np.ndarray
    observed: np.ndarray
    rendered: np.ndarray
    soft: bool = False

    def roi_levels(self, kind: str) -> np.ndarray:
        """The ROI image (h, w) uint8 of ``kind`` (``observed`` or ``rendered``): 255 on a mask,
        the probability times 255 for soft evidence."""
        rows, cols = self.roi.shape
        if kind == "observed" and self.soft:
            return self.observed.reshape(rows, cols)
        return np.unpackbits(getattr(self, kind), count=rows * cols).reshape(rows, cols) * np.uint8(255)

    def image(self, kind: str) -> np.ndarray:
        """The full-size mono8 image (H, W) uint8 of ``kind``: 255 on the mask (the probability
        times 255 for soft evidence), 0 elsewhere."""
        shape = (int(self.camera.height), int(self.camera.width))
        return self.roi.paste(self.roi_levels(kind), shape, fill=0)


def frame_masks(estimator: Estimator, frame: Frame, result: FrameEstimate,
                frame_ids: dict[str, str]) -> tuple[SensorMasks, ...]:
    """The masks of every sensor observed in ``frame`` (the estimator's last step), the
    rendered ones at ``result``'s estimate; ``frame_ids`` maps sensor names to TF frames. The
    cameras are given as the step used them (one whose extrinsics it corrected turned:
    ``estimator/extrinsics.py``)."""
    likelihood = estimator.last_likelihood
    if likelihood is None or (likelihood.frame.index, likelihood.frame.stamp_ns) != (frame.index, frame.stamp_ns):
        raise ValueError(f"frame {frame.index}: the estimator's last step was another frame")
    frame = likelihood.frame
    obs = likelihood.observation
    rendered = likelihood.rendered_masks(result.T_ee_object)
    out = []
    for name in obs.sensors:
        img = frame.image(name)
        observed, soft = obs.masks[name], obs.masks[name].dtype != np.bool_
        out.append(SensorMasks(
            sensor=name, frame_id=frame_ids[name], tactile=name in obs.tactile, roi=obs.rois[name], camera=img.camera,
            T_world_sensor=np.array(img.T_world_sensor, dtype=np.float64),
            observed=soft_observed(observed)[0] if soft else np.packbits(observed.ravel()),
            rendered=np.packbits(rendered[name].ravel()), soft=soft,
        ))
    return tuple(out)


def topic(sensor: str, kind: str) -> str:
    """``/mvtop/debug/<sensor>/<kind>``, characters a ROS name cannot hold replaced by ``_``."""
    return f"{TOPIC_PREFIX}/{re.sub(r'[^A-Za-z0-9_]', '_', sensor)}/{kind}"


def write_debug_images(w: LogWriter, result: FrameEstimate, world_frame: str, skip_tf: Iterable[str] = ()) -> int:
    """The debug topics of one frame's ``result`` (see the module doc; nothing when it keeps
    no masks); ``skip_tf`` names frames whose TF the track already writes (``ee``). Returns
    the number of images written."""
    masks = result.debug_masks
    skip = {world_frame, *skip_tf}
    tf = {m.frame_id: m.T_world_sensor for m in masks if m.frame_id not in skip}
    if tf:
        w.write_tf([(world_frame, f, T) for f, T in tf.items()], result.stamp_ns)
    for m in masks:
        w.write_camera_info(topic(m.sensor, "camera_info"), m.camera, result.stamp_ns, m.frame_id)
        for kind in KINDS:
            w.write_image(topic(m.sensor, kind), m.image(kind), result.stamp_ns, m.frame_id, encoding="mono8")
    return 2 * len(masks)
