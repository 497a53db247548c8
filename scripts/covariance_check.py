"""NEES of each run's final covariance in a `mvtop benchmark accuracy` folder, as the particles'
spread alone and with the evidence's widths added, times each of ``--factors``
(`output.covariance: particles_and_evidence`, `output.evidence_width_factor`,
estimator/evidence.py), recomputed from each run's summary.json by `mvtop eval`'s own NEES.
Prints one line per run and, per method and object, the fraction within the chi-square 95 % bound.
With ``--suspect F`` also the covariance a run reports when at least the fraction F of its frames
left some pose axis or a rival mode open (``output.suspect_unpinned_fraction``), or whose last frame has a rival mode:
the particles' spread plus the grasp prior's about the estimate (``nees_suspect``,
``GraspPriorModel.covariance_about`` without a symmetry fold; other runs keep the default widths x3).
A run whose last frame was flagged reported the particles' spread plus the prior's covariance alone
(as the code did before ``covariance_about``; runs made since are not told apart). A run made with
``output.evidence_profile`` reported the wider of the probe's and the profile's widths per axis (both in
summary.json's evidence block), times the factor; ``--profile-factors G`` adds, for such runs, the NEES
with the probe's widths times ``output.evidence_width_factor`` against the profile's times each G
(``nees_profile_xG``: the wider per axis).
Usage: .venv/bin/python scripts/covariance_check.py BENCH_DIR [--factors 1,3] [--suspect 0.4]
       [--profile-factors 1,2,3] [--json OUT.json]"""
import argparse
import collections
import csv
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import yaml

from mvtop_cli.config import OutputConfig, load_config
from mvtop_cli.estimator.evidence import evidence_covariance
from mvtop_cli.estimator.prior import GraspPriorModel
from mvtop_cli.filter.health import is_suspect
from mvtop_cli.geometry import se3
from mvtop_cli.pipelines.evaluate import evaluate
from mvtop_cli.pipelines.track import closed_frames


def nees_with(run: Path, log: Path, covariance: np.ndarray) -> float:
    summary = json.loads((run / "summary.json").read_text())
    summary["final"] = dict(summary["final"], covariance_ee=covariance.tolist())
    with tempfile.TemporaryDirectory() as tmp:
        track = Path(tmp) / "track"
        shutil.copytree(run, track, ignore=shutil.ignore_patterns("eval", "track.mcap"))
        (track / "summary.json").write_text(json.dumps(summary))
        return float(evaluate(track, log, None, Path(tmp) / "eval")["final"]["nees"])


def axis_widths(evidence: dict, key: str) -> np.ndarray:
    """(6,) widths [m, rad] of summary.json's evidence block ``KEY_translation_m`` / ``KEY_rotation_deg``
    (null: open, inf)."""
    return np.array([np.inf if v is None else v for v in evidence[f"{key}_translation_m"]]
                    + [np.inf if v is None else np.radians(v) for v in evidence[f"{key}_rotation_deg"]])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path)
    ap.add_argument("--factors", default="1,3", help="comma-separated evidence width factors")
    ap.add_argument("--suspect", type=float, default=None, help="suspect_unpinned_fraction to test")
    ap.add_argument("--profile-factors", default="", help="comma-separated factors of the profile's widths")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    factors = [float(f) for f in args.factors.split(",")]
    profile_factors = [float(f) for f in args.profile_factors.split(",") if f]
    rows = []
    for run in sorted((args.bench / "runs").iterdir()):
        if not (run / "result.json").is_file():
            continue
        result = json.loads((run / "result.json").read_text())
        summary = json.loads((run / "summary.json").read_text())
        ev = summary.get("evidence", {}).get("final")
        if ev is None:
            continue
        obj, seed, method = run.name.rsplit("_", 2)
        log = args.bench / "scenes" / f"{obj}_{seed}" / "log.mcap"
        cfg = load_config(run / "config.resolved.yaml")
        prior_model = GraspPriorModel(cfg.grasp_prior, cfg.search.bound)
        prior = prior_model.sigma
        with (run / "track.csv").open() as fh:
            track = list(csv.DictReader(fh))
        last_flags = track[-1]["flags"].split("|")
        flagged = "suspect_estimate" in last_flags or "rival_mode" in last_flags
        widths = axis_widths(ev, "likelihood_sigma")
        profile = axis_widths(ev, "profile_sigma") if "profile_sigma_translation_m" in ev else None
        used = widths if profile is None else np.maximum(widths, profile)  # EvidenceReport.widths
        reported = np.array(summary["final"]["covariance_ee"])
        # runs made before output.covariance existed reported the particles' spread alone, before
        # output.evidence_width_factor existed the widths as they are
        output = yaml.safe_load((run / "config.resolved.yaml").read_text()).get("output") or {}
        mode, made_with = output.get("covariance", "particles"), float(output.get("evidence_width_factor", 1.0))
        particles = (reported if mode == "particles" else reported - np.diag(prior**2) if flagged
                     else reported - evidence_covariance(used, prior, made_with))
        row = {"run": run.name, "object": obj, "method": method, "bound": result["final"]["nees_bound"],
               "insertable": result["final"]["insertable"], "error_mm": result["final"]["pose_error_mm"],
               "nees_particles": nees_with(run, log, particles)}
        for f in factors:
            row[f"nees_evidence_x{f:g}"] = nees_with(run, log, particles + evidence_covariance(widths, prior, f))
        for g in profile_factors if profile is not None else ():
            wider = np.maximum(made_with * widths, g * profile)
            added = np.diag(prior**2) if flagged else evidence_covariance(wider, prior)
            row[f"nees_profile_x{g:g}"] = nees_with(run, log, particles + added)
        if args.suspect is not None:
            rivals = {int(r["frame"]) for r in track if "rival_mode" in r["flags"].split("|")}
            closed = closed_frames(summary["evidence"], rivals)
            row["suspect"] = is_suspect(sum(not p for p in closed), len(closed), args.suspect)
            f = summary["final"]["T_ee_object"]
            T_ee_est = se3.from_quat_xyzw(np.array(f["quaternion_xyzw"]), np.array(f["translation_m"]))
            added = (prior_model.covariance_about(T_ee_est) if row["suspect"] or "rival_mode" in last_flags
                     else evidence_covariance(widths, prior, OutputConfig().evidence_width_factor))
            row["nees_suspect"] = nees_with(run, log, particles + added)
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    keys = ["nees_particles"] + [f"nees_evidence_x{f:g}" for f in factors]
    if args.suspect is not None:
        keys.append("nees_suspect")
    profile_keys = [f"nees_profile_x{g:g}" for g in profile_factors]
    groups = collections.defaultdict(list)
    for r in rows:
        groups[(r["method"], "all")].append(r)
        groups[(r["method"], r["object"])].append(r)
    for (method, obj), rs in sorted(groups.items()):
        within = {k: sum(r[k] <= r["bound"] for r in rs) for k in keys}
        print(f"{method:7s} {obj:10s} {len(rs):3d} runs, NEES within the 95 % bound: particles {within[keys[0]]}, "
              + ", ".join(f"evidence x{f:g} {within[k]}" for f, k in zip(factors, keys[1:]))
              + (f", suspect -> prior about the estimate {within['nees_suspect']}" if args.suspect is not None else "")
              + "".join(f", probe x its run's factor | profile x{k.rsplit('x', 1)[1]} "
                        f"{sum(r[k] <= r['bound'] for r in rs if k in r)}" for k in profile_keys))


if __name__ == "__main__":
    main()
