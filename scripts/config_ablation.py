"""Re-run one method on the simulated logs of a `mvtop benchmark accuracy` folder with config keys
changed, and compare with that folder's own runs (same logs, same seeds).

Usage: .venv/bin/python scripts/config_ablation.py BENCH OUT METHOD KEY=VALUE [KEY=VALUE ...]
       [--scenes conn1_3000,...]
e.g.   scripts/config_ablation.py bench-3000 ablation-edges M-VTOP edges.gain=3
Resumable (a run with a result.json is kept); run it twice in parallel with disjoint --scenes to
use two cores. Prints per run and per object: within the clearance, median insertion error,
NEES within its bound, before -> after.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from mvtop_cli.benchmarks.accuracy import MODALITY_SETS
from mvtop_cli.config import load_config, parse_settings
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate
from mvtop_cli.pipelines.evaluate import evaluate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("bench", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("method", choices=sorted(MODALITY_SETS))
    ap.add_argument("overrides", nargs="+", metavar="KEY=VALUE")
    ap.add_argument("--scenes", default="")
    a = ap.parse_args()
    settings = parse_settings(a.overrides, "KEY=VALUE")
    scenes = sorted(p.name for p in (a.bench / "scenes").iterdir())
    if a.scenes:
        scenes = [s for s in scenes if s in a.scenes.split(",")]
    rows = []
    for name in scenes:
        scene, run = a.bench / "scenes" / name, a.out / f"{name}_{a.method}"
        if not (run / "result.json").exists():
            seed = int(name.rsplit("_", 1)[1])
            estimate(scene / "log.mcap", load_config(scene / "config.yaml", settings), run,
                     EstimateOptions(modalities=MODALITY_SETS[a.method], num_particles=None, seed=seed))
            report = evaluate(run, scene / "log.mcap", None, run / "eval")
            (run / "result.json").write_text(json.dumps({"final": report["final"]}))
        after = json.loads((run / "result.json").read_text())["final"]
        before = json.loads((a.bench / "runs" / f"{name}_{a.method}" / "result.json").read_text())["final"]
        rows.append((name.rsplit("_", 1)[0], before, after))
        print(f"{name:15s} {before['insertion_error_mm']:.3f} -> {after['insertion_error_mm']:.3f} mm", flush=True)
    for obj in sorted({r[0] for r in rows}) + ["all"]:
        sel = [r for r in rows if obj in ("all", r[0])]
        ok = [sum(r[i]["insertable"] for r in sel) for i in (1, 2)]
        med = [np.median([r[i]["insertion_error_mm"] for r in sel]) for i in (1, 2)]
        nees = [sum(r[i]["nees_within_bound"] for r in sel) for i in (1, 2)]
        print(f"{obj:10s} within clearance {ok[0]} -> {ok[1]} of {len(sel)}; median {med[0]:.3f} -> {med[1]:.3f} mm; "
              f"NEES within bound {nees[0]} -> {nees[1]}")


if __name__ == "__main__":
    main()
