"""M-VTOP end to end on simulated grasps whose log records one camera turned: per object and grasp,
the benchmark's 30-frame log of that seed (`mvtop benchmark accuracy`'s simulation, default scene),
one camera (front or side, drawn from the seed) recorded turned by a random angle uniform in
--turn-deg about a random axis of its optical frame (scripts/extrinsics_check.py's draw), then
`estimate` with the scene config and the grasp's seed as the filter seed (as the benchmark runs
it) and `evaluate`. Prints how many runs end within the clearance and far off (above --far
clearances), how many of those raise `suspect_estimate`, and how many cameras the extrinsics check
corrected; with --compare, the same grasps' runs of a benchmark results file (the log as recorded).
--rows appends one JSON line per run (resumable; gzip-compressed when ROWS ends in .gz).
Usage: .venv/bin/python scripts/turned_camera_runs.py --rows ROWS [--objects cube,...]
       [--seeds 1000-1009] [--turn-deg 1,3] [--compare RESULTS.jsonl.gz] [--settings KEY=VALUE ...]"""
import argparse
import gzip
import json
import tempfile
from pathlib import Path

import numpy as np
import yaml
from extrinsics_check import random_turn, resumable_rows
from perturb_extrinsics import perturb_log

from mvtop_cli.config import load_config
from mvtop_cli.geometry import se3
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate
from mvtop_cli.pipelines.evaluate import evaluate
from mvtop_cli.pipelines.simulate import SimulateOptions, simulate, write_scene_config
from mvtop_cli.sim.episode import EpisodeOptions

CAMERAS = {"front": "front_optical", "side": "side_optical"}


def run_grasp(obj: str, seed: int, turn_deg: tuple[float, float], settings: dict) -> dict:
    """One grasp: the log with one camera turned, estimated and evaluated."""
    camera = sorted(CAMERAS)[seed % 2]
    turn = random_turn(seed, camera, *turn_deg)
    T = np.eye(4)
    T[:3, :3] = se3.rotvec_to_matrix(np.radians(turn))
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        simulate(obj, seed, d / "log.mcap", SimulateOptions(episode=EpisodeOptions(frames=30)))
        if not perturb_log(d / "log.mcap", d / "turned.mcap", CAMERAS[camera], T):
            raise SystemExit(f"{obj} {seed}: no /tf_static transform of {CAMERAS[camera]}")
        cfg = load_config(write_scene_config(obj, d / "config.yaml"), settings)
        summary = estimate(d / "turned.mcap", cfg, d / "out", EstimateOptions(seed=seed))
        report = evaluate(d / "out", d / "turned.mcap", None, d / "out" / "eval")
    final = report["final"]
    return {"object": obj, "seed": seed, "camera": camera, "true_turn_deg": turn.round(4).tolist(),
            "settings": settings, "extrinsics": summary["extrinsics"], "warning_counts": summary["warning_counts"],
            "insertion_error_mm": final["insertion_error_mm"], "clearance_mm": report["clearance_mm"],
            "nees": final.get("nees"), "nees_bound": final.get("nees_bound")}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", type=Path, required=True)
    ap.add_argument("--objects", default="cube,shaft_peg,plug,conn1,conn2")
    ap.add_argument("--seeds", default="1000-1009")
    ap.add_argument("--turn-deg", default="1,3")
    ap.add_argument("--far", type=float, default=5.0)
    ap.add_argument("--compare", type=Path)
    ap.add_argument("--settings", nargs="*", default=[], help="dotted config keys, KEY=VALUE (YAML values)")
    args = ap.parse_args()
    turn = tuple(float(x) for x in args.turn_deg.split(","))
    settings = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.settings)}
    def make_row(obj: str, seed: int) -> dict:
        row = run_grasp(obj, seed, turn, settings)
        print(f"{obj} {seed}: {row['camera']} turned {np.linalg.norm(row['true_turn_deg']):.2f} deg, "
              f"{row['insertion_error_mm'] / row['clearance_mm']:.2f} clearances, {row['warning_counts']}", flush=True)
        return row

    rows = resumable_rows(args.rows, args.objects, args.seeds, make_row)

    def tally(name: str, runs: list[tuple[float, bool]]) -> None:
        within = [s for r, s in runs if r <= 1.0]
        far = [s for r, s in runs if r > args.far]
        print(f"{name}: {len(runs)} runs, within the clearance {len(within)}, far off {len(far)} "
              f"({sum(far)} flagged suspect_estimate); flagged within the clearance {sum(within)}")

    tally("turned camera", [(r["insertion_error_mm"] / r["clearance_mm"],
                             r["warning_counts"].get("suspect_estimate", 0) > 0) for r in rows.values()])
    corrected = sum(any(e and e["corrected"] for e in r["extrinsics"].values()) for r in rows.values())
    print(f"cameras corrected: {corrected} of {len(rows)}")
    if args.compare:
        recorded = {}
        with gzip.open(args.compare, "rt") as f:
            for line in f:
                r = json.loads(line)
                bm = r["benchmark"]
                key = (bm["object"], bm["seed"])
                if bm["method"] == "M-VTOP" and bm.get("scene", "default") == "default" and key in rows:
                    flagged = bm.get("warning_counts", {}).get("suspect_estimate", 0) > 0
                    recorded[key] = (r["final"]["insertion_error_mm"] / r["clearance_mm"], flagged)
        tally("the same grasps as recorded", list(recorded.values()))


if __name__ == "__main__":
    main()
