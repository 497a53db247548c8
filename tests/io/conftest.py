"""Fixtures for the io tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from _io_scene import write_scene


@pytest.fixture(scope="module")
def scene_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "scene.mcap"
    write_scene(path)
    return path
