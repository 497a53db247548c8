"""One offscreen OpenGL (EGL) context per process, shared by every pyrender user.

pyrender's EGL platform terminates the EGL display when any OffscreenRenderer is deleted,
which breaks every other renderer in the process; so mvtop creates a single renderer, resizes
its viewport per use, and deletes it only at interpreter exit.
"""

from __future__ import annotations

import atexit
import os

import numpy as np

from ..errors import MvtopError

_RENDERER = None


def import_pyrender():
    """Import pyrender for offscreen EGL rendering.

    Sets ``PYOPENGL_PLATFORM=egl`` unless the user chose a platform (it must be set before
    OpenGL is imported), and restores ``np.infty`` (removed in numpy 2, still used by
    pyrender 0.1.45 when it computes mesh bounds).
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if not hasattr(np, "infty"):
        np.infty = np.inf  # type: ignore[attr-defined]
    import pyrender

    return pyrender


def offscreen_renderer(width: int, height: int):
    """The process's pyrender.OffscreenRenderer with its viewport set to ``width`` x ``height``."""
    global _RENDERER
    pr = import_pyrender()
    if _RENDERER is None:
        try:
            _RENDERER = pr.OffscreenRenderer(width, height)
        except Exception as err:
            raise MvtopError(
                f"cannot create an OpenGL context (PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r}; "
                f"EGL needs libegl1, libegl-mesa0, libgl1-mesa-dri and libgbm1): {err}"
            ) from err
        atexit.register(_delete)
    _RENDERER.viewport_width, _RENDERER.viewport_height = int(width), int(height)
    return _RENDERER


def _delete() -> None:
    global _RENDERER
    if _RENDERER is not None:
        try:
            _RENDERER.delete()
        except Exception:  # the context may already be gone at exit
            pass
        _RENDERER = None
