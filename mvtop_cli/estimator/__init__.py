"""The M-VTOP model and the estimator's per-frame step, free of io, config loading and the
command line: frames in, estimates out.

- ``scene``: the object and environment geometry (mask renderer, occluders, contact grid).
- ``observation``: the masking backends and each frame's observed masks in their ROIs
  (Algorithm 1-2).
- ``likelihood``: the frame's log-likelihood of a pose (eq. 1-2 weighted IoU sum, eq. 8-9
  contact term).
- ``motion``: the in-hand motion model (Algorithm 4); ``prior``: the grasp prior.
- ``estimator``: ``Estimator.step`` runs one frame with the filter of ``filter/``.
"""

from .estimator import Estimator, FrameEstimate
from .scene import OBJECT_ID, SceneModel

__all__ = ["OBJECT_ID", "Estimator", "FrameEstimate", "SceneModel"]
