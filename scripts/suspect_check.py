"""How the run-level `suspect_estimate` warning (filter/health.py: suspect_warning) separates the
runs of `mvtop benchmark accuracy` folders that end far off from those within the clearance,
recomputed from each run's summary.json (the per-frame evidence diagnostic's ``pinned`` and
``rival`` columns: a frame that left some axis or a rival mode open counts; in folders written
before the ``rival`` column, the frames track.csv flags ``rival_mode``, and before the ``pinned``
column, a frame whose widest translation or rotation width is null left some axis open) and eval
report, so folders made before the warning existed count too. Far off: final insertion error above FAR x the clearance
(5); within: at most the clearance. Prints, per source and method, the far-off runs flagged and
the within-clearance runs flagged (false alarms), at each --thresholds value.

A source is a benchmark folder (its runs/), a folder of run folders (scripts/config_ablation.py's
output), a .jsonl.gz written by --export (one line per run: source, run, method, the insertion
error over the clearance, the per-frame ``closed`` flags (older exports: ``pinned``), and
``other``: whether a cause beside the open frames raises the warning anyway), which keeps what
this needs from run folders that are not kept (benchmarks/accuracy/suspect/), or a benchmark's
results.jsonl.gz whose runs kept ``benchmark.suspect`` (summary.json ``suspect``: the count of
open frames stands for the flags, whose order the fraction does not need). A run with another
cause (a rival mode, sensors that disagree, a camera left turned) counts as flagged at every
threshold.
Usage: .venv/bin/python scripts/suspect_check.py SOURCE [SOURCE ...] [--thresholds 0.3,0.4,0.5]
       [--far 5] [--probe-only] [--export OUT.jsonl.gz]"""
import argparse
import collections
import csv
import gzip
import json
from pathlib import Path

from mvtop_cli.filter.health import suspect_warning
from mvtop_cli.pipelines.track import closed_frames


def records(source: Path, probe_only: bool = False) -> list[dict]:
    """One record per finished run of ``source``; from run folders with ``probe_only``, a frame
    is open only where the probe's widths are or a rival stood (``pipelines.track.closed_frames``)."""
    if source.suffix == ".gz":
        with gzip.open(source, "rt") as f:
            lines = [json.loads(line) for line in f]
        if lines and "benchmark" in lines[0]:  # a benchmark's results
            return [from_result(source, r) for r in lines if "suspect" in r["benchmark"]]
        return lines
    base = source / "runs" if (source / "runs").is_dir() else source
    out = []
    for run in sorted(base.iterdir()):
        if not ((run / "summary.json").is_file() and (run / "eval" / "report.json").is_file()):
            continue
        summary = json.loads((run / "summary.json").read_text())
        report = json.loads((run / "eval" / "report.json").read_text())
        out.append({"source": str(source), "run": run.name, "method": run.name.rsplit("_", 1)[1],
                    "ratio": report["final"]["insertion_error_mm"] / report["clearance_mm"],
                    "closed": closed_frames(summary["evidence"], rival_frames(run), probe_only),
                    "other": other_cause(summary.get("suspect", {}).get("causes", []))})
    return out


def from_result(source: Path, row: dict) -> dict:
    """The record of one line of a benchmark's results.jsonl.gz that kept ``benchmark.suspect``."""
    b, s = row["benchmark"], row["benchmark"]["suspect"]
    return {"source": str(source), "run": f"{b['object']}_{b['seed']}_{b['method']}", "method": b["method"],
            "ratio": row["final"]["insertion_error_mm"] / row["clearance_mm"],
            "closed": [False] * s["unpinned_frames"] + [True] * (s["evidence_frames"] - s["unpinned_frames"]),
            "other": other_cause(s["causes"])}


def rival_frames(run: Path) -> set[int]:
    """The frames of run folder ``run`` whose track.csv flags hold ``rival_mode``."""
    with open(run / "track.csv", newline="") as f:
        return {int(row["frame"]) for row in csv.DictReader(f) if "rival_mode" in row["flags"].split("|")}


def other_cause(causes: list[str]) -> bool:
    """Whether a run's ``suspect`` causes hold one beside the open frames, which raises the
    warning at any threshold."""
    return bool(set(causes) - {"unpinned"})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sources", nargs="+", type=Path)
    ap.add_argument("--thresholds", default="0.4")
    ap.add_argument("--far", type=float, default=5.0)
    ap.add_argument("--export", type=Path)
    ap.add_argument("--probe-only", action="store_true",
                    help="run folders: count a frame open only where the probe's widths are, as before the "
                         "profile's open axes counted")
    a = ap.parse_args()
    thresholds = [float(t) for t in a.thresholds.split(",")]
    everything = []
    for source in a.sources:
        recs = records(source, a.probe_only)
        everything += recs
        by_source = collections.defaultdict(list)
        for r in recs:
            by_source[r["source"]].append(r)
        for name, rs in by_source.items():
            counts = collections.defaultdict(collections.Counter)
            for r in rs:
                kind = "far" if r["ratio"] > a.far else "within" if r["ratio"] <= 1.0 else None
                for m in (r["method"], "all"):
                    counts[m]["runs"] += 1
                    if kind:
                        counts[m][kind] += 1
                        closed = r.get("closed", r.get("pinned"))
                        for t in thresholds:
                            counts[m][(kind, t)] += r.get("other", False) or suspect_warning(closed, t) is not None
            for m, c in sorted(counts.items(), key=lambda kv: (kv[0] == "all", kv[0])):
                parts = [f"threshold {t:g}: far off flagged {c[('far', t)]} of {c['far']}, "
                         f"within the clearance flagged {c[('within', t)]} of {c['within']}" for t in thresholds]
                print(f"{name} {m:6s} {c['runs']:3d} runs; " + "; ".join(parts))
    if a.export:
        with gzip.open(a.export, "wt") as f:
            f.writelines(json.dumps(r) + "\n" for r in everything)


if __name__ == "__main__":
    main()
