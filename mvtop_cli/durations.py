"""Durations as people read them, for progress lines and summaries."""

from __future__ import annotations


def format_duration(seconds: float) -> str:
    """``42 s``, ``7 min 5 s`` or ``3 h 12 min``."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {s % 3600 // 60} min"
