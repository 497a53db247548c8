"""Shared by the test folders: pytest puts this folder on ``sys.path``, so helper modules here
(``_track_decode``) can be imported by tests in any subfolder. The session keeps mvtop's cache
(contact grids, ``io.cache``) in a folder of its own, removed after it, never in the user's
``~/.cache/mvtop``; subprocesses inherit it."""

import os
import shutil
import tempfile

_CACHE: list[str] = []


def pytest_configure(config):
    _CACHE.append(tempfile.mkdtemp(prefix="mvtop-test-cache-"))
    os.environ["MVTOP_CACHE_DIR"] = _CACHE[-1]


def pytest_unconfigure(config):
    for folder in _CACHE:
        shutil.rmtree(folder, ignore_errors=True)
