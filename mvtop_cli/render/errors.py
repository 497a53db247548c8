"""Errors of the render package."""

from mvtop_cli.errors import MvtopError


class RenderError(MvtopError):
    """A renderer cannot run here (e.g. no OpenGL context can be created)."""
