"""Mask renderers: the object silhouette in a camera and its gel penetration in a tactile sensor.

All particles of one sensor are rendered and scored in one call, inside a region of interest:

    renderer = NumbaMaskRenderer()
    renderer.add_mesh("object", mesh.vertices, mesh.faces)          # once, metres
    roi = roi_for_particles(renderer.mesh("object"), T_cam_obj, camera)   # (N, 4, 4) poses
    observed = roi.crop(observed_full_mask)
    scores = renderer.score_masks("object", T_cam_obj, camera, roi, observed,
                                  observed_outside=roi.outside_area(observed_full_mask))

``NumbaMaskRenderer`` (CPU, parallel over particles) is the fast path;
``PyrenderMaskRenderer`` (OpenGL over EGL, one render per pose) is the reference. The
numba kernels compile on first use and are cached on disk.
"""

from mvtop_cli.render.base import MaskRenderer, Occluder, RenderMode, penetration_depth
from mvtop_cli.render.iou import iou_from_counts, iou_scores
from mvtop_cli.render.mesh import RenderMesh
from mvtop_cli.render.numba_renderer import NumbaMaskRenderer
from mvtop_cli.render.roi import Roi, roi_for_particles, roi_from_bounds

__all__ = [
    "MaskRenderer",
    "NumbaMaskRenderer",
    "Occluder",
    "RenderMesh",
    "RenderMode",
    "Roi",
    "iou_from_counts",
    "iou_scores",
    "penetration_depth",
    "roi_for_particles",
    "roi_from_bounds",
]


def __getattr__(name: str):
    # The reference renderer imports pyrender (and selects EGL) only when asked for.
    if name == "PyrenderMaskRenderer":
        from mvtop_cli.render.pyrender_renderer import PyrenderMaskRenderer

        return PyrenderMaskRenderer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
