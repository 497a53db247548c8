"""Print particle x sensor evaluations per second (render + IoU) for the batched numba renderer
and for one pyrender call per particle, for 2 cameras + 2 tactile sensors.

    .venv/bin/python scripts/bench_render.py [--particles 250 1000 4000] [--mesh part.obj ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import trimesh
from numba import set_num_threads

from mvtop_cli.benchmarks.render_speed import benchmark_render, default_meshes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, nargs="+", default=[250, 1000, 4000])
    parser.add_argument("--mesh", type=Path, action="append", default=[], help="extra mesh file in metres (repeatable)")
    parser.add_argument("--only-extra", action="store_true", help="skip the built-in cube and connector box")
    parser.add_argument("--no-reference", action="store_true", help="skip the pyrender per-particle path")
    parser.add_argument("--reference-max", type=int, default=64, help="particles per sensor timed for pyrender")
    parser.add_argument("--repeats", type=int, default=7, help="batched timings: best of this many")
    parser.add_argument("--threads", type=int, default=None, help="numba threads (default: all cores)")
    args = parser.parse_args()
    if args.threads:
        set_num_threads(args.threads)
    meshes = {} if args.only_extra else default_meshes()
    for path in args.mesh:
        mesh = trimesh.load(path, force="mesh")
        meshes[f"{path.stem} ({len(mesh.faces)} faces)"] = mesh
    rows = benchmark_render(
        args.particles,
        meshes=meshes,
        reference=not args.no_reference,
        reference_max_particles=args.reference_max,
        repeats=args.repeats,
    )
    print(f"{'mesh':<44} {'particles':>9} {'evals/s':>10} {'ms/frame':>9} {'pyrender evals/s':>17}  ROIs (h, w)")
    for r in rows:
        ref = f"{r['reference_evals_per_s']:.0f}" if r["reference_evals_per_s"] else "-"
        print(
            f"{r['mesh']:<44} {r['particles']:>9} {r['evals_per_s']:>10.0f} {r['seconds'] * 1e3:>9.1f} "
            f"{ref:>17}  {r['roi_shapes']}"
        )
    print(f"(numba threads: {rows[0]['threads'] if rows else '-'}; one eval = one particle in one sensor)")


if __name__ == "__main__":
    main()
