"""Write the scene meshes built in mvtop_cli.sim as OBJ files (metres, deterministic bytes).

Usage: python scripts/export_meshes.py [OUT_DIR]   (default: configs/meshes in this repository).
Writes <name>.obj and <name>_receptacle.obj for every object, finger.obj and board.obj.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mvtop_cli.pipelines.simulate import export_scene_meshes

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "configs" / "meshes"


def export_all(out_dir: Path) -> list[Path]:
    """Write every object, receptacle, finger and board mesh into ``out_dir``; return the paths."""
    return export_scene_meshes(out_dir)


def main(argv: list[str]) -> int:
    out_dir = Path(argv[0]) if argv else DEFAULT_OUT
    for path in export_all(out_dir):
        print(f"{path} ({path.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
