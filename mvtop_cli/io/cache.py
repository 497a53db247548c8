"""Where mvtop keeps what it can rebuild but need not: the environment's signed-distance grids
(``contact.sdf.EnvironmentSDF``), keyed by a hash of the posed meshes, box and resolution.

``MVTOP_CACHE_DIR`` names the folder; set to an empty string it turns caching off. Without it,
``$XDG_CACHE_HOME/mvtop`` or ``~/.cache/mvtop``. Deleting the folder is always safe: every entry
is rebuilt on demand, bit for bit the same.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "MVTOP_CACHE_DIR"


def cache_dir() -> Path | None:
    """The cache folder (not created here), or None when ``MVTOP_CACHE_DIR`` is set empty."""
    value = os.environ.get(ENV_VAR)
    if value is not None:
        return Path(value).expanduser() if value.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "mvtop"
