"""The outputs of an estimate: track.mcap, track.csv, summary.json and config.resolved.yaml."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..config import Config, dump_config
from ..estimator import FrameEstimate
from ..estimator.evidence import finite_or_none
from ..filter.health import count_warnings, left_open, sensor_report, suspect_causes, suspect_warning, warning_lines
from ..geometry import se3
from ..io.atomic import atomic_output
from ..io.mcap_writer import LogWriter
from ..io.track_scene import OBJECT_FRAME, object_triangles, write_track_scene
from .debug_images import write_debug_images


def run_summary(results: list[FrameEstimate], cfg: Config, log_path: Path, elapsed: float, skipped,
             run_warnings: list[dict] | tuple = ()) -> dict:
    """The run's summary.json. ``run_warnings``: warnings not tied to a frame (meshes, units),
    reported with the frames' failure-mode warnings under ``warnings`` (counted per kind in
    ``warning_counts``); ``sensors`` gives each sensor's agreement with the estimate and
    weight factor, ``suspect`` every reason for the run's ``suspect_estimate`` record that holds
    at its end (see filter/health.py)."""
    last = results[-1]
    q = se3.to_quat_xyzw(last.T_world_object)
    qe = se3.to_quat_xyzw(last.T_ee_object)
    flags: dict[str, int] = {}
    warnings = list(run_warnings)
    agreement = []
    for r in results:
        for fl in r.flags:
            flags[fl] = flags.get(fl, 0) + 1
        warnings.extend(r.warnings)
        agreement.append((r.index, getattr(r, "sensor_iou", {})))
    closed = [not left_open(r.evidence.pinned, getattr(r, "rival", None)) for r in results if r.evidence is not None]
    rivals = [getattr(last, "rival", None), getattr(last, "disagreement", None)]
    suspect = suspect_warning(closed, cfg.output.suspect_unpinned_fraction, rivals[0] or rivals[1])
    left_turned = [a for a in getattr(last, "extrinsics", {}).values() if a is not None and a.suspect]
    if suspect is None and left_turned:
        suspect = left_turned[0].suspect_warning()
    if suspect is not None:
        warnings.append(suspect)
    out = {
        "log": str(log_path),
        "object": cfg.object.name,
        "modalities": list(cfg.modalities),
        "masking": {"camera": cfg.masking.camera.backend, "tactile": cfg.masking.tactile.backend},
        "particles": cfg.filter.num_particles,
        "seed": cfg.filter.seed,
        "frames_processed": len(results),
        "frames_skipped": len(skipped),
        "run_time_s": round(elapsed, 3),
        "time_per_frame_s": round(elapsed / len(results), 4),
        "final": {
            "stamp_ns": last.stamp_ns,
            "T_world_object": {"translation_m": last.T_world_object[:3, 3].tolist(), "quaternion_xyzw": q.tolist()},
            "T_ee_object": {"translation_m": last.T_ee_object[:3, 3].tolist(), "quaternion_xyzw": qe.tolist()},
            "covariance_ee": last.covariance.tolist(),
            "translation_std_m": float(np.sqrt(np.trace(last.covariance[:3, :3]) / 3)),
            "rotation_std_deg": float(np.degrees(np.sqrt(np.trace(last.covariance[3:, 3:]) / 3))),
            "ess": last.ess,
        },
        "flags": flags,
        "warnings": warnings,
        "warning_counts": count_warnings(warnings),
        "suspect": suspect_causes(closed, cfg.output.suspect_unpinned_fraction, rivals, bool(left_turned)),
        "sensors": sensor_report(agreement, warnings),
        "evidence": evidence_report(results),
        "extrinsics": extrinsics_report(last),
    }
    if last.T_world_object_gt is not None:
        dt = last.T_world_object[:3, 3] - last.T_world_object_gt[:3, 3]
        out["final"]["ground_truth_translation_error_mm"] = float(1000 * np.linalg.norm(dt))
        out["final"]["ground_truth_rotation_error_deg"] = float(
            np.degrees(se3.rotation_angle(last.T_world_object[:3, :3], last.T_world_object_gt[:3, :3]))
        )
    return out


def evidence_report(results: list[FrameEstimate]) -> dict:
    """summary.json's ``evidence``: the final frame's diagnostic in full (per-sensor IoU at the
    estimate, the likelihood's width per axis, ``estimator/evidence.py``) and, per frame, the
    worst sensor IoU, the probe's widest translation [m] / rotation [deg] width (null: no evidence,
    or a flat likelihood), whether the evidence pinned every axis (``EvidenceReport.pinned``: the
    probe's and the latest profile's widths) and whether a rival mode stood (what the
    ``suspect_estimate`` warning counts: ``filter.health.left_open``); and
    the first frame's leave-one-out gains per sensor [nats] (``search.disagreement_margin``; null:
    the check did not run)."""
    num = finite_or_none
    frames = [[r.index, num(r.evidence.min_iou), num(r.evidence.sigma_translation_m),
               num(r.evidence.sigma_rotation_deg), r.evidence.pinned, getattr(r, "rival", None) is not None]
              for r in results if r.evidence is not None]
    final = next((r.evidence.as_dict() for r in reversed(results) if r.evidence is not None), None)
    checked = next((r for r in results if getattr(r, "leave_one_out", None) is not None), None)
    left_out = None if checked is None else {"frame": checked.index, "others_gain_nats": checked.leave_one_out}
    return {"final": final, "per_frame": {"columns": ["frame", "min_iou", "sigma_translation_m", "sigma_rotation_deg",
                                                      "pinned", "rival"],
                                          "rows": frames}, "leave_one_out": left_out}


def pinned_frames(evidence: dict, probe_only: bool = False) -> list[bool]:
    """Per frame with evidence, whether it pinned every pose axis, from a summary.json ``evidence``
    block (``evidence_report``): its ``pinned`` column, or with ``probe_only`` or for folders
    written before that column, the probe's widths alone (a null width left an axis open)."""
    per_frame = evidence["per_frame"]
    columns, rows = per_frame["columns"], per_frame["rows"]
    if "pinned" in columns and not probe_only:
        k = columns.index("pinned")
        return [bool(r[k]) for r in rows]
    return [r[2] is not None and r[3] is not None for r in rows]


def closed_frames(evidence: dict, rival_frames: set[int] | None = None, probe_only: bool = False) -> list[bool]:
    """Per frame with evidence, whether it left the pose closed (``not filter.health.left_open``):
    every axis pinned (``pinned_frames``) and no rival mode standing, from the ``rival`` column,
    or for folders written before it from ``rival_frames``, the frames track.csv flags
    ``rival_mode``."""
    per_frame = evidence["per_frame"]
    columns, rows = per_frame["columns"], per_frame["rows"]
    if "rival" in columns:
        k = columns.index("rival")
        rivals = [bool(r[k]) for r in rows]
    else:
        rivals = [r[0] in (rival_frames or set()) for r in rows]
    return [p and not q for p, q in zip(pinned_frames(evidence, probe_only), rivals)]


def extrinsics_report(last: FrameEstimate) -> dict:
    """summary.json's ``extrinsics``: per camera, what the extrinsics check found on its first
    image (``estimator/extrinsics.py``): the frame, the turn [deg] about the camera's optical x,
    y, z axes that lines the known scene up with the image best, its angle, the outline score
    with the recorded extrinsics and with the turn, the share the turn adds, the contour samples
    read, how far apart the meshes want the camera turned (``mesh_spread_deg``, null unless
    misaligned) and the verdict (``misaligned``, ``corrected``, ``one_turn``,
    ``at_edge``); null where the known scene gave too few samples to judge by. Empty when the
    check is off or no camera was seen."""
    out = {}
    for name, a in getattr(last, "extrinsics", {}).items():
        out[name] = None if a is None else {
            "frame": a.frame, "turn_deg": [round(v, 4) for v in a.turn_deg], "angle_deg": round(a.angle_deg, 4),
            "score_recorded": round(a.score_recorded, 1), "score_turned": round(a.score_turned, 1),
            "gain": round(a.gain, 4), "samples": a.samples,
            "mesh_spread_deg": None if a.mesh_spread_deg is None else round(a.mesh_spread_deg, 4),
            "misaligned": a.misaligned, "corrected": a.corrected, "one_turn": a.one_turn, "at_edge": a.at_edge,
        }
    return out


STAGES = ("read_s", "masking_s", "search_s", "filter_s", "checks_s", "diagnostics_s", "likelihood_s", "step_s")


def stage_timing(results, startup_s: float) -> dict:
    """Where the time went: ``startup_s`` (meshes, contact grid, log index) and, for the first
    frame and as the mean over the later frames, the wall seconds per stage (``read_s`` decoding
    the frame, ``masking_s`` the observation, ``search_s`` the filter's searches (the first
    frame's search of the grasp prior, the re-search check), ``filter_s`` prediction and
    refinement, ``checks_s`` the mode and rival checks (their searches and refinements),
    ``diagnostics_s`` the rest: the evidence diagnostic, the sensor watch, the jump check (the
    five add up to ``step_s``, the whole step), ``likelihood_s`` all scoring),
    the likelihood calls and poses scored; ``tracked_frames`` the later frames the tracking mode
    took (``filter.tracking_particles``); ``log_s`` the time the frames span and
    ``wall_over_log`` the frames' wall time (reading and steps, after the first) over it."""
    rows = [r.timings for r in results if r.timings]
    if not rows:
        return {}

    def stats(sel: list[dict]) -> dict:
        out = {k: round(float(np.mean([t.get(k, 0.0) for t in sel])), 6) for k in STAGES}
        out["likelihood_calls"] = float(np.mean([t.get("likelihood_calls", 0) for t in sel]))
        out["poses_scored"] = float(np.mean([t.get("poses_scored", 0) for t in sel]))
        return out

    later = rows[1:]
    stamps = [r.stamp_ns for r in results]
    log_s = (stamps[-1] - stamps[0]) / 1e9
    later_wall = sum(t.get("read_s", 0.0) + t.get("step_s", 0.0) for t in later)
    interval_s = log_s / max(len(stamps) - 1, 1)
    return {
        "startup_s": round(startup_s, 3),
        "first_frame": stats(rows[:1]),
        "later_frames_mean": stats(later) if later else {},
        "frames": len(rows),
        "tracked_frames": sum(bool(t.get("tracked", False)) for t in later),
        "log_s": round(log_s, 3),
        "wall_over_log": round(later_wall / (interval_s * len(later)), 3) if later and interval_s > 0 else None,
    }


def warning_report(summary: dict) -> list[str]:
    """The summary's warnings for the terminal: one line per kind, saying in how many frames."""
    return warning_lines(summary.get("warnings", []), summary["frames_processed"])


TRACK_CSV_HEADER = ("frame,stamp_ns,x_m,y_m,z_m,qx,qy,qz,qw,ee_x_m,ee_y_m,ee_z_m,ee_qx,ee_qy,ee_qz,ee_qw,"
                    "std_translation_m,std_rotation_deg,ess,contact,"
                    "evidence_min_iou,evidence_sigma_translation_m,evidence_sigma_rotation_deg,mask_mode,flags")


def _evidence_cells(r: FrameEstimate) -> list[str]:
    """The evidence diagnostic's track.csv cells: empty without evidence, and a width left empty
    where the likelihood does not pin some axis (the track holds no nan or inf)."""
    ev = r.evidence
    if ev is None:
        return ["", "", ""]
    iou = "" if ev.min_iou is None else f"{ev.min_iou:.4f}"
    st, sr = ev.sigma_translation_m, ev.sigma_rotation_deg
    return [iou, f"{st:.9f}" if np.isfinite(st) else "", f"{sr:.6f}" if np.isfinite(sr) else ""]


def track_csv_row(r: FrameEstimate) -> str:
    """One frame's line of track.csv: pose in world and in ee (metres, quaternion xyzw), RMS
    spread (translation [m], rotation [deg]), ESS, contact, the evidence diagnostic (the worst
    sensor IoU at the estimate, the likelihood's widest translation [m] and rotation [deg]
    width, ``estimator/evidence.py``), mask mode and flags."""
    q = se3.to_quat_xyzw(r.T_world_object)
    qe = se3.to_quat_xyzw(r.T_ee_object)
    st = np.sqrt(np.trace(r.covariance[:3, :3]) / 3)
    sr = np.degrees(np.sqrt(np.trace(r.covariance[3:, 3:]) / 3))
    vals = [*r.T_world_object[:3, 3], *q, *r.T_ee_object[:3, 3], *qe]
    contact = "" if r.contact is None else str(int(r.contact))
    return ",".join([str(r.index), str(r.stamp_ns)] + [f"{v:.9f}" for v in vals]
                    + [f"{st:.9f}", f"{sr:.6f}", f"{r.ess:.2f}", contact, *_evidence_cells(r), r.mask_mode,
                       "|".join(r.flags)])


def write_track(out_dir: Path, results: list[FrameEstimate], cfg: Config, summary: dict) -> None:
    """track.mcap, track.csv, summary.json and config.resolved.yaml, each written atomically;
    track.mcap also holds each sensor's observed and rendered masks of the frames whose
    results keep them (``debug_images``)."""
    with LogWriter(out_dir / "track.mcap") as w:
        write_track_scene(w, [r.stamp_ns for r in results], np.stack([r.T_world_object for r in results]),
                          np.stack([r.T_ee_object for r in results]),
                          object_triangles(cfg.object.mesh, cfg.object.units), cfg.frames.world, cfg.frames.ee)
        for r in results:
            w.write_pose("/mvtop/object_pose", r.T_world_object, r.stamp_ns, cfg.frames.world)
            w.write_pose("/mvtop/object_pose_ee", r.T_ee_object, r.stamp_ns, cfg.frames.ee)
            w.write_pose_array("/mvtop/particles", r.particles_world, r.stamp_ns, cfg.frames.world)
            write_debug_images(w, r, cfg.frames.world, skip_tf=(cfg.frames.ee, OBJECT_FRAME))
    lines = [TRACK_CSV_HEADER] + [track_csv_row(r) for r in results]
    with atomic_output(out_dir / "track.csv", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    with atomic_output(out_dir / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    with atomic_output(out_dir / "config.resolved.yaml", "w") as fh:
        fh.write(dump_config(cfg))
