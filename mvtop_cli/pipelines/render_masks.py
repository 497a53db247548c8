"""``mvtop render-masks``: what the estimator saw, frame by frame and sensor by sensor.

For each chosen frame and sensor: the image, the observed object mask, the CAD model's mask
rendered at the estimate (from a track) and at the ground truth (when the log has it), and an
overlay like the paper's figure 6 (observed mask in blue, rendered mask in yellow, IoU written
on it); a contact sheet of all sensors per frame; and a video of the sheets over the log.
Without a track the masks are rendered at the ground truth, or at a pose given by the caller,
which is how a wrong extrinsic or grasp pose shows at once. With a track whose run corrected a
camera's extrinsics (summary.json's ``extrinsics``), that camera is used turned as the run used
it, so its overlays show what the estimator saw (``masks.json`` names the turn).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..config import Config
from ..errors import MvtopError, TrackError
from ..estimator.extrinsics import turned_camera
from ..estimator.observation import Observer
from ..estimator.scene import OBJECT_ID, SceneModel
from ..geometry import se3
from ..io.atomic import atomic_output, atomic_path
from ..io.frames import FrameReader
from ..io.mcap_reader import McapLog
from ..render.roi import Roi
from .estimate import log_topics, sensor_topics

OBSERVED_BGR = (255, 120, 0)  # blue (paper figure 6: predicted mask)
RENDERED_BGR = (0, 215, 255)  # yellow (rendered mask)
TRUTH_BGR = (80, 220, 80)  # green outline: ground truth
_SHEET_TILE = (320, 240)


@dataclass(frozen=True)
class RenderMasksOptions:
    frames: tuple[int, ...] | None = None  # frame indices, None = all
    pose_ee: np.ndarray | None = None  # T_ee_object to render at instead of a track
    video: bool = True


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    u = np.logical_or(a, b).sum()
    return 1.0 if u == 0 else float(np.logical_and(a, b).sum() / u)


def read_track_poses(track_dir: Path) -> dict[int, np.ndarray]:
    """``T_world_object`` (4, 4) per stamp [ns] from an estimate folder's track.csv."""
    path = Path(track_dir) / "track.csv"
    if not path.is_file():
        raise TrackError(f"{path}: not found (expected the track.csv of an `mvtop estimate` output folder)")
    poses = {}
    try:
        with path.open() as fh:
            for row in csv.DictReader(fh):
                q = np.array([float(row[k]) for k in ("qx", "qy", "qz", "qw")])
                t = np.array([float(row[k]) for k in ("x_m", "y_m", "z_m")])
                poses[int(row["stamp_ns"])] = se3.from_quat_xyzw(q, t)
    except (KeyError, ValueError) as err:
        raise TrackError(f"{path}: malformed row ({err}); expected the columns written by `mvtop estimate`") from None
    if not poses:
        raise TrackError(f"{path}: no rows")
    return poses


def read_track_turns(track_dir: Path) -> dict[str, list[float]]:
    """Per camera the run corrected, the turn [deg] about its optical x, y, z axes it used, from an
    estimate folder's summary.json (``extrinsics``; none when the folder has no summary.json or
    the run checked no camera)."""
    path = Path(track_dir) / "summary.json"
    if not path.is_file():
        return {}
    try:
        found = json.loads(path.read_text()).get("extrinsics") or {}
        return {name: [float(v) for v in a["turn_deg"]] for name, a in found.items()
                if a is not None and a.get("corrected")}
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise TrackError(f"{path}: malformed extrinsics block ({err}); expected the summary.json written by "
                         "`mvtop estimate`") from None


def _overlay(image: np.ndarray, observed: np.ndarray | None, rendered: np.ndarray | None,
             truth: np.ndarray | None, label: str) -> np.ndarray:
    """BGR overlay: observed mask filled blue, rendered mask filled yellow, truth outlined."""
    out = (image[:, :, ::-1].astype(np.float32) * 0.55).astype(np.uint8)
    for mask, colour in ((observed, OBSERVED_BGR), (rendered, RENDERED_BGR)):
        if mask is not None and mask.any():
            out[mask] = (0.5 * out[mask] + 0.5 * np.array(colour)).astype(np.uint8)
    if truth is not None and truth.any():
        cnt, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, cnt, -1, TRUTH_BGR, 1)
    scale = max(0.4, image.shape[1] / 800)
    (w, h), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    out[: h + 12, : w + 12] = (out[: h + 12, : w + 12] * 0.3).astype(np.uint8)
    cv2.putText(out, label, (6, h + 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise MvtopError(f"{path}: could not encode the image")
    with atomic_output(path) as fh:
        fh.write(buf.tobytes())


def render_masks(
    log_path: Path, cfg: Config, out_dir: Path, track_dir: Path | None = None,
    options: RenderMasksOptions = RenderMasksOptions(), progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Write the per-frame, per-sensor mask images, sheets, video and masks.json into
    ``out_dir``; returns the content of masks.json."""
    scene = SceneModel(cfg, build_contact=False)
    track = read_track_poses(track_dir) if track_dir is not None else None
    turns = read_track_turns(track_dir) if track_dir is not None else {}
    observer = Observer(cfg)
    gel = {t.name: t.gel_distance_m for t in cfg.sensors.tactile}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary: dict = {"log": str(log_path), "track": None if track_dir is None else str(track_dir),
                     "cameras_turned_deg": turns, "frames": []}
    sheets: list[Path] = []
    with McapLog(log_path) as log:
        reader = FrameReader(log, sensor_topics(cfg), log_topics(cfg))
        total = log.summary().topic(cfg.sensors.cameras[0].image_topic).message_count if cfg.sensors.cameras else 0
        for frame in reader:
            if options.frames is not None and frame.index not in options.frames:
                continue
            if track is not None:
                stamp = min(track, key=lambda s: abs(s - frame.stamp_ns))
                T_est = track[stamp] if abs(stamp - frame.stamp_ns) <= 1_000_000 else None
            elif options.pose_ee is not None:
                T_est = frame.T_world_ee @ options.pose_ee
            else:
                T_est = None
            T_gt = frame.T_world_object_gt
            T_ref = T_est if T_est is not None else T_gt
            if T_ref is None:
                raise MvtopError(f"{log_path}: frame {frame.index} has no ground truth; give --track or --pose-ee")
            entry = {"frame": frame.index, "stamp_ns": frame.stamp_ns, "contact": frame.contact, "sensors": {}}
            tiles = []
            for name, img in [*frame.cameras.items(), *frame.tactile.items()]:
                tactile = name in frame.tactile
                if name in turns:  # the run used this camera turned (its extrinsics check)
                    img = replace(img, T_world_sensor=turned_camera(img.T_world_sensor, turns[name]))
                full = Roi.full(img.camera)
                occ = [] if tactile else scene.occluders(
                    img.T_world_sensor, lambda f, img=img: reader.tf.lookup(cfg.frames.world, f, img.stamp_ns)
                )
                kw = dict(
                    mode="tactile", gel_distance_m=gel[name],
                    penetration_threshold_m=cfg.masking.tactile_depth_threshold_m,
                ) if tactile else {}

                def render(T_world_object, img=img, full=full, occ=occ, kw=kw):
                    if T_world_object is None:
                        return None
                    T = se3.invert(img.T_world_sensor) @ T_world_object
                    return scene.renderer.render_masks(OBJECT_ID, T[None], img.camera, full, occ, **kw)[0]

                at_est, at_gt = render(T_est), render(T_gt)
                if tactile:
                    observed = observer.tactile_mask(img)
                elif observer.recorded:  # the masks recorded in the log (masking.camera.backend: topic)
                    observed = observer.recorded_mask(img)
                else:  # the estimator's promptable mode at the reference pose
                    prompt = render(T_ref)
                    observed = observer.camera_prompt(img, prompt) if prompt.any() else None
                rendered = at_est if at_est is not None else at_gt
                rec = {
                    "iou_estimate": None if observed is None or at_est is None else iou(observed, at_est),
                    "iou_truth": None if observed is None or at_gt is None else iou(observed, at_gt),
                }
                entry["sensors"][name] = rec
                base = out_dir / f"frame_{frame.index:04d}_{name}"
                _write_png(base.with_name(base.name + "_image.png"), img.image[:, :, ::-1])
                for suffix, mask in (("observed", observed), ("estimate", at_est), ("truth", at_gt)):
                    if mask is not None:
                        _write_png(base.with_name(f"{base.name}_{suffix}.png"), mask.astype(np.uint8) * 255)
                shown = rec["iou_estimate"] if at_est is not None else rec["iou_truth"]
                which = "estimate" if at_est is not None else "truth"
                label = f"{name} frame {frame.index}: IoU({which}) = " + ("n/a" if shown is None else f"{shown:.3f}")
                overlay = _overlay(img.image, observed, rendered, at_gt if at_est is not None else None, label)
                _write_png(base.with_name(base.name + "_overlay.png"), overlay)
                tiles.append(cv2.resize(overlay, _SHEET_TILE, interpolation=cv2.INTER_AREA))
            sheet = np.hstack(tiles)
            sheet_path = out_dir / f"frame_{frame.index:04d}_sheet.png"
            _write_png(sheet_path, sheet)
            sheets.append(sheet_path)
            summary["frames"].append(entry)
            if progress is not None:
                progress(len(sheets), len(options.frames) if options.frames else total)
    if not sheets:
        raise MvtopError(f"{log_path}: none of the requested frames is in the log")
    if options.video:
        _write_video(out_dir / "masks.mp4", sheets)
        summary["video"] = "masks.mp4"
    with atomic_output(out_dir / "masks.json", "w") as fh:
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    return summary


def _write_video(path: Path, sheets: list[Path], fps: float = 5.0) -> None:
    first = cv2.imread(str(sheets[0]))
    h, w = first.shape[:2]
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp.with_suffix(".mp4")), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if not writer.isOpened():
            raise MvtopError(f"{path}: OpenCV cannot write mp4 video here")
        for p in sheets:
            writer.write(cv2.imread(str(p)))
        writer.release()
        tmp.with_suffix(".mp4").rename(tmp)
