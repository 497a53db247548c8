"""The ``topic`` camera backend: object masks recorded in the log by an external segmenter.

A segmentation node on the robot (SAM2, Mask R-CNN, ...) publishes one mask per camera
image on the camera's ``mask_topic`` (sensor_msgs Image mono8/mono16 or a png
CompressedImage); the log reader pairs each mask with its image by stamp and hands it on as
``SensorImage.mask``, (H, W) uint16 labels with 0 = background. This backend turns the labels
into the object mask: every non-zero pixel, or with the ``label`` option only the pixels of
that label id (a segmenter that labels several objects). It is the paper's supervised setting
(section IV-A: masks from a trained segmenter) as users record it: the mask is the
observation itself, so Algorithm 1-2's selection among proposals is not needed.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import MaskContext


class RecordedMaskBackend:
    """Object masks from recorded label images; ``label`` the object's label id (1-65535),
    None for every non-zero label."""

    def __init__(self, label: int | None = None):
        if label is not None and (isinstance(label, bool) or not isinstance(label, int) or not 1 <= label <= 65535):
            raise ConfigError(f"option 'label': expected an integer 1-65535, got {label!r}")
        self.label = label

    def object_mask(self, labels: np.ndarray) -> np.ndarray:
        """The (H, W) bool object mask of a recorded (H, W) label image."""
        labels = np.asarray(labels)
        return labels == self.label if self.label is not None else labels != 0

    def proposals(self, image: np.ndarray, context: MaskContext | None = None) -> list[np.ndarray]:
        """The recorded mask (``context.extras["recorded_mask"]``) as the one proposal; none
        when the image has no recorded mask."""
        labels = None if context is None else context.extras.get("recorded_mask")
        return [] if labels is None else [self.object_mask(labels)]
