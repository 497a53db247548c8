"""Regenerate the shipped sample logs and scene configs.

Usage: python scripts/make_samples.py [--frames N]
Writes sample_logs/NAME.mcap (seed 1), configs/NAME.yaml and the object file
configs/objects/NAME.yaml for every object of `mvtop simulate --list`, plus the meshes in
configs/meshes/. Deterministic: running it again
reproduces the same bytes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mvtop_cli.pipelines.simulate import SimulateOptions, simulate, write_scene_config
from mvtop_cli.sim.episode import EpisodeOptions
from mvtop_cli.sim.object_file import write_object_file
from mvtop_cli.sim.objects import builtin_object_file, list_objects

REPO = Path(__file__).resolve().parents[1]
SEED = 1
OBJECT_FILE_HEADER = ("# mvtop object file of a built-in object, written by scripts/make_samples.py from\n"
                      "# mvtop_cli/sim/objects.py; mesh paths are relative to this file.\n")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--objects", nargs="*", default=list_objects())
    args = parser.parse_args(argv)
    (REPO / "sample_logs").mkdir(exist_ok=True)
    for name in args.objects:
        out = REPO / "sample_logs" / f"{name}.mcap"
        summary = simulate(
            name, SEED, out, SimulateOptions(episode=EpisodeOptions(frames=args.frames), jpeg_quality=85)
        )
        write_scene_config(name, REPO / "configs" / f"{name}.yaml")
        (REPO / "configs" / "objects").mkdir(exist_ok=True)
        write_object_file(builtin_object_file(name), REPO / "configs" / "objects" / f"{name}.yaml", OBJECT_FILE_HEADER)
        print(f"{out.relative_to(REPO)}: {summary.frames} frames, {summary.contact_frames} in contact, "
              f"{summary.bytes / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
