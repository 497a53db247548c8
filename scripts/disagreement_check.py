"""How the first frame's leave-one-out check (`search.disagreement_margin`, README: Sensors that
disagree) falls on the grasps of a committed `mvtop benchmark accuracy` folder: per grasp, the log
simulated anew with 4 frames (the first frame is that of the benchmark's 30-frame log), its first
frame estimated (M-VTOP, the grasp's seed as the filter seed) and each sensor's leave-one-out gain
read from summary.json's `evidence.leave_one_out`; the run's outcome (final insertion error over
the clearance, its `suspect_estimate` flag) from the folder's results.jsonl.gz, whose estimates
the check does not change. Prints, at each --margins value, the far-off runs (above --far
clearances) it flags and the runs within the clearance it flags, alone and with the run's own
flags; --rows appends one JSON line per grasp (resumable: grasps already there are skipped).
Usage: .venv/bin/python scripts/disagreement_check.py RESULTS.jsonl.gz --scene default|hard
       --rows ROWS.jsonl [--objects cube,...] [--seeds 1000-1099] [--margins 4,6,8,10] [--far 5]"""
import argparse
import gzip
import json
import tempfile
from pathlib import Path

from mvtop_cli.config import load_config
from mvtop_cli.pipelines.estimate import EstimateOptions, estimate
from mvtop_cli.pipelines.simulate import SimulateOptions, scene_options, simulate, write_scene_config
from mvtop_cli.sim.episode import EpisodeOptions


def first_frame_gains(obj: str, seed: int, scene: str) -> dict:
    """Per sensor the leave-one-out gain [nats] (None: not judged) of grasp ``seed``'s first frame."""
    with tempfile.TemporaryDirectory() as d:
        log = Path(d) / "log.mcap"
        simulate(obj, seed, log, scene_options(SimulateOptions(episode=EpisodeOptions(frames=4)), scene))
        cfg = load_config(write_scene_config(obj, Path(d) / "config.yaml"))
        estimate(log, cfg, Path(d) / "out", EstimateOptions(seed=seed, max_frames=1))
        summary = json.loads((Path(d) / "out" / "summary.json").read_text())
    return summary["evidence"]["leave_one_out"]["others_gain_nats"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("results", type=Path)
    ap.add_argument("--scene", required=True, choices=("default", "hard"))
    ap.add_argument("--rows", type=Path, required=True)
    ap.add_argument("--objects", default="cube,shaft_peg,plug,conn1,conn2")
    ap.add_argument("--seeds", default="1000-1099")
    ap.add_argument("--margins", default="4,6,8,10")
    ap.add_argument("--far", type=float, default=5.0)
    args = ap.parse_args()
    outcome = {}
    with gzip.open(args.results, "rt") as f:
        for line in f:
            r = json.loads(line)
            b = r["benchmark"]
            if b["method"] == "M-VTOP" and b.get("scene", "default") == args.scene:
                outcome[(b["object"], b["seed"])] = (r["final"]["insertion_error_mm"] / r["clearance_mm"],
                                                     b.get("warning_counts", {}).get("suspect_estimate", 0) > 0)
    rows = {}
    if args.rows.exists():
        for line in args.rows.read_text().splitlines():
            r = json.loads(line)
            rows[(r["object"], r["seed"])] = r
    a, b = (int(x) for x in args.seeds.split("-"))
    for seed in range(a, b + 1):
        for obj in args.objects.split(","):
            if (obj, seed) in rows or (obj, seed) not in outcome:
                continue
            row = {"object": obj, "seed": seed, "scene": args.scene, "gains": first_frame_gains(obj, seed, args.scene)}
            rows[(obj, seed)] = row
            with args.rows.open("a") as f:
                f.write(json.dumps(row) + "\n")
    for margin in (float(m) for m in args.margins.split(",")):
        far = [k for k in rows if k in outcome and outcome[k][0] > args.far]
        within = [k for k in rows if k in outcome and outcome[k][0] <= 1.0]
        flagged = {k for k in rows if max([g for g in rows[k]["gains"].values() if g is not None] or [-1e9]) >= margin}
        print(f"margin {margin:g} nats: far off flagged {len(flagged & set(far))} of {len(far)} "
              f"({sum(k in flagged or outcome[k][1] for k in far)} with the run's own flags); within the clearance "
              f"flagged {len(flagged & set(within))} of {len(within)} "
              f"({sum(k in flagged or outcome[k][1] for k in within)} with the run's own flags)")


if __name__ == "__main__":
    main()
