"""``mvtop eval``: score an estimate output folder against ground truth and write a report.

The truth is the log's ground-truth topic (``geometry_msgs/PoseStamped`` in the world
frame, interpolated at each track stamp) or a file holding one world pose, the nominal
inserted pose at the final frame. Definitions of every number: docs/metrics.md.
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..config import Config, load_config
from ..errors import ConfigError, LogError, MvtopError, TrackError
from ..eval import metrics as M
from ..eval import report as R
from ..eval.clearance import continuous_scores, insertable
from ..eval.continuous import closest_in_rotation
from ..geometry import se3
from ..io.atomic import atomic_output

REPORT_SCHEMA = "mvtop.eval/1"
TRACK_COLUMNS = (
    "frame", "stamp_ns", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw",
    "ee_x_m", "ee_y_m", "ee_z_m", "ee_qx", "ee_qy", "ee_qz", "ee_qw",
    "std_translation_m", "std_rotation_deg", "ess",
)
NEES_PROBABILITY = 0.95
# Added to covariance diagonals before inverting: (1 um)^2 and (1 urad)^2. Far below any
# spread a particle filter reports, it only keeps a collapsed set (zero variance) from
# dividing by zero: such a set gets a huge, finite NEES, which is what it deserves.
COVARIANCE_FLOOR = np.array([1e-12] * 3 + [1e-12] * 3)
SURFACE_SAMPLES = 1000  # ADD / ADI points; ~1 mm spacing on a connector, < 1 % noise in the mean
SAMPLE_SEED = 0
BOP_SCENE_ID = 0
BOP_OBJ_ID = 1
GT_FILE_KEYS = ("translation_m", "quaternion_xyzw")


# --- inputs ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Track:
    """A pose track read from an estimate folder; arrays have one entry per row of track.csv.

    ``T_world_object`` and ``T_ee_object`` (N, 4, 4); ``std_*`` the per-frame spreads
    (``sqrt(trace/3)`` of the covariance blocks, [m] and [rad]); ``final_covariance_ee``
    (6, 6) the last frame's full covariance from summary.json.
    """

    path: Path
    frames: np.ndarray
    stamps_ns: np.ndarray
    T_world_object: np.ndarray
    T_ee_object: np.ndarray
    std_translation_m: np.ndarray
    std_rotation_rad: np.ndarray
    ess: np.ndarray
    final_covariance_ee: np.ndarray
    summary: dict

    @property
    def T_world_ee(self) -> np.ndarray:
        """(N, 4, 4) end-effector poses implied by the two object poses of each row."""
        return self.T_world_object @ se3.invert(self.T_ee_object)


def _number(value: str, path: Path, line: int, column: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TrackError(f"{path}: line {line}: column {column!r}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise TrackError(f"{path}: line {line}: column {column!r}: expected a finite number, got {value!r}")
    return v


def _integer(value: str, path: Path, line: int, column: str) -> int:
    try:
        return int(value.strip())
    except (AttributeError, ValueError):
        raise TrackError(f"{path}: line {line}: column {column!r}: expected an integer, got {value!r}") from None


def read_track(track_dir: Path) -> Track:
    """Read track.csv and summary.json of an ``mvtop estimate`` output folder; TrackError
    naming the file and what was expected on anything missing or malformed."""
    track_dir = Path(track_dir)
    if not track_dir.is_dir():
        raise TrackError(f"{track_dir}: track folder not found (expected the output folder of mvtop estimate)")
    csv_path = track_dir / "track.csv"
    if not csv_path.is_file():
        raise TrackError(f"{csv_path}: file not found (expected the pose track written by mvtop estimate)")
    try:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise TrackError(f"{csv_path}: cannot read the pose track ({err})") from None
    if not rows:
        raise TrackError(f"{csv_path}: file is empty (expected a header line and one line per frame)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in TRACK_COLUMNS if c not in header]
    if missing:
        raise TrackError(
            f"{csv_path}: missing column(s) {', '.join(missing)} (expected the columns of mvtop estimate's track.csv)"
        )
    body = [(i + 2, r) for i, r in enumerate(rows[1:]) if any(cell.strip() for cell in r)]
    if not body:
        raise TrackError(f"{csv_path}: no frames (expected one line per frame after the header)")
    col = {c: header.index(c) for c in TRACK_COLUMNS}
    data = np.empty((len(body), len(TRACK_COLUMNS)))
    for k, (line, r) in enumerate(body):
        if len(r) < len(header):
            raise TrackError(f"{csv_path}: line {line}: {len(r)} fields (expected {len(header)} as in the header)")
        for j, c in enumerate(TRACK_COLUMNS):
            data[k, j] = _number(r[col[c]], csv_path, line, c)
    frames = np.array([_integer(r[col["frame"]], csv_path, line, "frame") for line, r in body], dtype=np.int64)
    stamps = np.array([_integer(r[col["stamp_ns"]], csv_path, line, "stamp_ns") for line, r in body], dtype=np.int64)
    d = {c: data[:, j] for j, c in enumerate(TRACK_COLUMNS)}
    if np.any(np.diff(stamps) < 0):
        line = body[int(np.argmax(np.diff(stamps) < 0)) + 1][0]
        raise TrackError(f"{csv_path}: line {line}: stamp_ns goes back in time (expected frames in time order)")
    q = np.stack([d["qx"], d["qy"], d["qz"], d["qw"]], axis=1)
    qe = np.stack([d["ee_qx"], d["ee_qy"], d["ee_qz"], d["ee_qw"]], axis=1)
    for name, quat in (("qx..qw", q), ("ee_qx..ee_qw", qe)):
        norms = np.linalg.norm(quat, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
        if len(bad):
            raise TrackError(
                f"{csv_path}: line {body[bad[0]][0]}: quaternion {name} has norm {norms[bad[0]]:.6g} "
                "(expected a unit quaternion)"
            )
    T_world = se3.from_quat_xyzw(
        q / np.linalg.norm(q, axis=1, keepdims=True), np.stack([d["x_m"], d["y_m"], d["z_m"]], axis=1)
    )
    T_ee = se3.from_quat_xyzw(
        qe / np.linalg.norm(qe, axis=1, keepdims=True), np.stack([d["ee_x_m"], d["ee_y_m"], d["ee_z_m"]], axis=1)
    )
    summary = _read_summary(track_dir / "summary.json", int(stamps[-1]))
    return Track(
        path=track_dir, frames=frames, stamps_ns=stamps, T_world_object=T_world, T_ee_object=T_ee,
        std_translation_m=d["std_translation_m"], std_rotation_rad=np.radians(d["std_rotation_deg"]), ess=d["ess"],
        final_covariance_ee=summary["_covariance"], summary={k: v for k, v in summary.items() if k != "_covariance"},
    )


def _read_summary(path: Path, last_stamp_ns: int) -> dict:
    if not path.is_file():
        raise TrackError(f"{path}: file not found (expected the summary.json written by mvtop estimate)")
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise TrackError(f"{path}: not valid JSON ({err})") from None
    final = summary.get("final") if isinstance(summary, dict) else None
    if not isinstance(final, dict) or "covariance_ee" not in final:
        raise TrackError(f"{path}: final.covariance_ee: missing (expected the 6x6 covariance of the final pose)")
    try:
        cov = np.asarray(final["covariance_ee"], dtype=np.float64)
    except (TypeError, ValueError):
        cov = np.zeros(0)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        raise TrackError(f"{path}: final.covariance_ee: expected a 6x6 matrix of finite numbers, got shape {cov.shape}")
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-15) or np.min(np.linalg.eigvalsh((cov + cov.T) / 2)) < -1e-12:
        raise TrackError(f"{path}: final.covariance_ee: expected a symmetric positive semi-definite matrix")
    stamp = final.get("stamp_ns")
    if stamp is not None and int(stamp) != last_stamp_ns:
        raise TrackError(
            f"{path}: final.stamp_ns is {stamp} but the last frame of track.csv has stamp_ns {last_stamp_ns} "
            "(expected the summary of the same run)"
        )
    return {**summary, "_covariance": (cov + cov.T) / 2}


def read_gt_file(path: Path) -> np.ndarray:
    """One world pose (4, 4) from a YAML or JSON file ``{translation_m: [x, y, z],
    quaternion_xyzw: [x, y, z, w]}``; ConfigError naming the file and key otherwise."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: ground-truth file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read ground-truth file ({err})") from None
    try:
        data = yaml.safe_load(text)  # JSON is YAML
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML/JSON ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with keys {', '.join(GT_FILE_KEYS)}")
    import difflib

    for k in data:
        if k not in GT_FILE_KEYS:
            hint = difflib.get_close_matches(str(k), GT_FILE_KEYS, n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else f" (expected {', '.join(GT_FILE_KEYS)})"
            raise ConfigError(f"{path}: {k}: unknown key{extra}")
    values = {}
    for key, n in zip(GT_FILE_KEYS, (3, 4)):
        v = data.get(key)
        ok = isinstance(v, list) and len(v) == n and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in v
        )
        if not ok or not all(math.isfinite(x) for x in v):
            raise ConfigError(f"{path}: {key}: expected a list of {n} numbers, got {v!r}")
        values[key] = np.asarray(v, dtype=np.float64)
    q = values["quaternion_xyzw"]
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise ConfigError(f"{path}: quaternion_xyzw: expected a unit quaternion, got norm {np.linalg.norm(q):.6g}")
    return se3.from_quat_xyzw(q / np.linalg.norm(q), values["translation_m"])


def ground_truth_from_log(log_path: Path, config: Config, stamps_ns: np.ndarray) -> tuple[np.ndarray, dict]:
    """Ground-truth ``T_world_object`` (N, 4, 4) at ``stamps_ns``, interpolated between the
    log's PoseStamped messages on the config's ground-truth topic; NaN where the messages do
    not cover a stamp (within the sync tolerance). Messages in another frame than the world
    are converted through the log's TF at each stamp, as ``estimate`` does (NaN where TF does
    not cover it). Also ``{"frame": the messages' frame, "cameras": {name: (K (N, 3, 3),
    T_world_camera (N, 4, 4))}}``, the calibrations and camera poses MSPD needs (empty when
    the log has no TF or camera topics), and "contact": the log's contact state at each stamp
    (a list of bool or None; None without TF and sensor topics). LogError if the log has no
    ground truth."""
    from ..io import ros2_msgs as rm
    from ..io.frames import header_stamp_ns
    from ..io.mcap_reader import McapLog
    from ..io.tf_buffer import PoseSeries

    topic = config.topics.ground_truth
    world = config.frames.world
    tol = int(round(config.sync_tolerance_s * 1e9))
    hint = "pass --gt FILE with the nominal final world pose to evaluate without it"
    n = len(stamps_ns)
    with McapLog(log_path) as log:
        summary = log.summary()
        if topic is None or not summary.has_topic(topic):
            raise LogError(
                f"{log_path}: no ground truth: topic {topic!r} not found (expected geometry_msgs/msg/PoseStamped "
                f"in {world!r} or a frame TF connects to it); {hint}"
            )
        info = summary.topic(topic)
        if rm.normalize_type(info.type) != rm.normalize_type(rm.POSE_STAMPED):
            raise LogError(f"{log_path}: topic {topic!r} has type {info.type!r} (expected {rm.POSE_STAMPED})")
        t, v, frame = [], [], None
        for m in log.messages(topic):
            f = str(m.msg.header.frame_id).lstrip("/")
            if frame is None:
                frame = f
            elif f != frame:
                raise LogError(
                    f"{log_path}: ground truth on {topic!r} changes frame from {frame!r} to {f!r} at log time "
                    f"{m.log_time_ns} ns (expected one frame)"
                )
            p, q = m.msg.pose.position, m.msg.pose.orientation
            t.append(header_stamp_ns(m.msg, m.log_time_ns))
            v.append([p.x, p.y, p.z, q.x, q.y, q.z, q.w])
        if not t:
            raise LogError(f"{log_path}: no ground truth: topic {topic!r} has no messages; {hint}")
        reader = _tf_reader(log, config)
        if frame != world and reader is None:
            raise LogError(
                f"{log_path}: ground truth on {topic!r} is in frame {frame!r}; expected {world!r}, or TF "
                f"({config.topics.tf!r}, {config.topics.tf_static!r}) and the configured sensors' topics to convert it"
            )
        out = np.full((n, 4, 4), np.nan)
        if frame == world:
            v = np.asarray(v, dtype=np.float64)
            series = PoseSeries(np.asarray(t, dtype=np.int64), v[:, :3],
                                v[:, 3:] / np.linalg.norm(v[:, 3:], axis=1, keepdims=True))
            for i, s in enumerate(stamps_ns):
                if series.covers(int(s), tol):
                    out[i] = series.at(int(s))
        else:
            for i, s in enumerate(stamps_ns):
                T = reader.ground_truth_at(int(s))
                if T is not None:
                    out[i] = T
        cameras = _camera_poses(reader, config, stamps_ns) if reader is not None else {}
        contact = None if reader is None else [reader.contact_at(int(s)) for s in stamps_ns]
    return out, {"frame": frame, "cameras": cameras, "contact": contact}


def _tf_reader(log, config: Config):
    """A FrameReader over the log's TF, contact signal, ground truth and calibrations (every
    configured sensor whose image and CameraInfo topics hold messages, whichever modalities
    the config enables), or None when the log has no TF or no such sensor."""
    from dataclasses import replace

    from ..config import MODALITIES
    from ..io.frames import FrameReader
    from .estimate import log_topics, sensor_topics

    summary = log.summary()

    def has(topic: str | None) -> bool:
        return topic is not None and summary.has_topic(topic) and summary.topic(topic).message_count > 0

    if not (has(config.topics.tf) or has(config.topics.tf_static)):
        return None
    every = sensor_topics(replace(config, modalities=MODALITIES))
    sensors = [s for s in every if has(s.image_topic) and has(s.info_topic)]
    if not sensors:
        return None
    return FrameReader(log, sensors, log_topics(config))


def _camera_poses(reader, config: Config, stamps_ns: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per camera the reader knows: K (N, 3, 3) and ``T_world_camera`` (N, 4, 4) at the stamps (NaN off TF)."""
    out = {}
    names = {s.name for s in reader.sensors if s.modality == "camera"}
    for c in config.sensors.cameras:
        if c.name not in names:
            continue
        frame = reader.sensor_frame(c.name)
        K = np.stack([reader.camera_at(c.name, int(s)).K for s in stamps_ns])
        T_world_cam = np.full((len(stamps_ns), 4, 4), np.nan)
        for i, s in enumerate(stamps_ns):
            try:
                T_world_cam[i] = reader.tf.lookup(config.frames.world, frame, int(s))
            except LogError:  # TF does not cover this stamp: no MSPD for this frame
                pass
        out[c.name] = (K, T_world_cam)
    return out


# --- the object -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObjectModel:
    """What the metrics need of the object, in its own frame [m].

    ``vertices`` the convex-hull vertices (exact for MSSD's maximum); ``samples`` points
    spread uniformly over the surface (ADD, ADI); ``corners`` the bounding box (8, 3); ``insertion_corners``
    the bounding box of the part within ``insertion_depth_m`` of the leading face;
    ``group`` the symmetry group (m, 4, 4), identity first.
    """

    name: str
    vertices: np.ndarray
    mesh_vertices: np.ndarray
    samples: np.ndarray
    corners: np.ndarray
    insertion_corners: np.ndarray
    group: np.ndarray
    clearance_m: float | None  # None: not configured, "insertable" is n/a
    insertion_depth_m: float
    continuous_symmetry: tuple[np.ndarray, np.ndarray] | None = None  # (axis (3,), point (3,) [m])
    directional_clearance: tuple[tuple[float, float], tuple[float, float]] | None = None  # [m], see config


def object_model(cfg: Config) -> ObjectModel:
    """Load the object's mesh and precompute its point sets and symmetry group."""
    from ..io.meshes import load_mesh

    obj = cfg.object
    mesh = load_mesh(obj.mesh, obj.units, what="object mesh")
    V = np.asarray(mesh.vertices, dtype=np.float64)
    try:
        hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    except Exception:  # qhull fails on flat meshes; all vertices are exact, just slower
        hull = V
    syms = np.stack([s.matrix() for s in obj.symmetries]) if obj.symmetries else None
    try:
        group = M.symmetry_group(syms, tol=1e-6)
    except ValueError as err:
        raise ConfigError(f"{cfg.source}: object.symmetries: {err}") from None
    samples = M.sample_surface(V, mesh.faces, SURFACE_SAMPLES, np.random.default_rng(SAMPLE_SEED))
    lo, hi = V.min(axis=0), V.max(axis=0)
    # The leading face is the object's lowest z (frames.md: +z points away from the
    # receptacle); a zero depth still checks that face.
    z_cut = lo[2] + max(obj.insertion_depth_m, 1e-9)
    ilo, ihi = M.clipped_bounds(V, mesh.edges_unique, min(z_cut, hi[2]))
    return ObjectModel(
        name=obj.name, vertices=hull, mesh_vertices=V, samples=samples, corners=M.box_corners(lo, hi),
        insertion_corners=M.box_corners(ilo, ihi), group=group, clearance_m=obj.clearance_m,
        insertion_depth_m=obj.insertion_depth_m, **_symmetry_and_clearance(obj),
    )


def _continuous_text(model: ObjectModel) -> str | None:
    """The continuous symmetry as the report states it, e.g. "about (0, 0, 1) through (0, 0, 0) mm"."""
    if model.continuous_symmetry is None:
        return None
    axis, point = model.continuous_symmetry
    return (f"every rotation about ({', '.join(f'{v:.6g}' for v in axis)}) through "
            f"({', '.join(f'{1e3 * v:.6g}' for v in point)}) mm")


def _symmetry_and_clearance(obj) -> dict:
    """ObjectModel's continuous symmetry and directional clearance from the config's object."""
    c, d = obj.continuous_symmetry, obj.directional_clearance
    return {"continuous_symmetry": None if c is None else (c.unit_axis(), np.asarray(c.point_m, dtype=np.float64)),
            "directional_clearance": None if d is None else (d.x_m, d.y_m)}


# --- scoring ----------------------------------------------------------------------------------------


def score_poses(
    model: ObjectModel,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    T_ee_est: np.ndarray | None = None,
    T_world_ee: np.ndarray | None = None,
    covariance_ee: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Every metric for poses (N, 4, 4) (world frame), SI units, one array (N,) each.

    With ``T_ee_est``, ``T_world_ee`` (N, 4, 4) and ``covariance_ee`` (N, 6, 6), also the
    NEES of the truth under the estimate's covariance, at the symmetric equivalent closest
    to the truth.
    """
    G = model.group
    sym = len(G) > 1
    k = M.closest_symmetry(T_est, T_gt, model.vertices, G)
    T_est_sym = T_est @ G[k]
    out = {
        "translation_error_m": M.translation_error(T_est_sym, T_gt),
        "rotation_error_rad": M.rotation_error(T_est_sym, T_gt),
        "translation_error_nosym_m": M.translation_error(T_est, T_gt),
        "rotation_error_nosym_rad": M.rotation_error(T_est, T_gt),
        "pose_error_m": M.pose_error_bbox(T_est, T_gt, model.corners, G),
        "pose_error_nosym_m": M.pose_error_bbox(T_est, T_gt, model.corners),
        "add_m": M.add(T_est, T_gt, model.samples),
        "add_sym_m": M.add(T_est, T_gt, model.samples, G),
        "adi_m": M.adi(T_est, T_gt, model.samples),
        "mssd_m": M.mssd(T_est, T_gt, model.vertices, G),
        "insertion_error_m": M.lateral_displacement(T_est, T_gt, model.insertion_corners, (0, 0, 1), G),
        "symmetry_index": k,
    }
    S = G[k]
    if model.continuous_symmetry is not None:  # exact minima over the angle (eval/continuous.py)
        continuous_scores(model, T_est, T_gt, out)
        # NEES against the equivalent closest in rotation: no error about the axis is left, where
        # the estimate's covariance (folded modulo the symmetry) has none either
        S = closest_in_rotation(T_est, T_gt, model.group, *model.continuous_symmetry)
        sym = True
    out["add_or_adi_m"] = out["adi_m"] if sym else out["add_m"]
    if model.clearance_m is None:  # no clearance configured: not decidable
        out["insertable"] = np.full(len(out["insertion_error_m"]), None, dtype=object)
    else:
        out["insertable"] = insertable(model, T_est, T_gt, out["insertion_error_m"])
    if covariance_ee is not None:
        T_ee_gt = se3.invert(T_world_ee) @ T_gt
        e = M.tangent_error(T_ee_est @ S, T_ee_gt)
        P = M.shift_covariance(covariance_ee, T_ee_est, S) + np.diag(COVARIANCE_FLOOR)
        out["nees"] = M.nees(e, P)
    return out


def mspd_per_camera(model: ObjectModel, T_world_est: np.ndarray, T_world_gt: np.ndarray,
                    cameras: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """MSPD [px] (BOP, ``metrics.mspd``) per camera and frame: the object poses moved into
    each camera's optical frame, ``T_camera_object = T_world_camera^-1 T_world_object``, and
    projected with that frame's calibration ``K``; NaN where the truth or TF is missing or a
    model vertex is behind the camera. ``cameras`` as ``ground_truth_from_log`` returns it."""
    out = {}
    for name, (K, T_world_cam) in cameras.items():
        vals = np.full(len(T_world_est), np.nan)
        ok = ~(np.isnan(T_world_gt).any(axis=(1, 2)) | np.isnan(T_world_cam).any(axis=(1, 2)))
        for i in np.flatnonzero(ok):
            T_cam_world = se3.invert(T_world_cam[i])
            T_est, T_gt = T_cam_world @ T_world_est[i], T_cam_world @ T_world_gt[i]
            z = np.concatenate([se3.transform_points(T, model.mesh_vertices)[..., 2].ravel()
                                for T in (T_est, T_gt @ model.group)])
            if np.all(z > 0):
                vals[i] = float(M.mspd(T_est, T_gt, K[i], model.mesh_vertices, model.group))
        out[name] = vals
    return out


def _stats(values: np.ndarray) -> dict[str, float | None]:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"median": None, "p95": None, "mean": None, "max": None}
    return {
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "mean": float(v.mean()),
        "max": float(v.max()),
    }


# Report keys: (name in the report, key in score_poses' output, factor from SI)
_METRICS = (
    ("translation_error_mm", "translation_error_m", 1e3),
    ("rotation_error_deg", "rotation_error_rad", 180.0 / math.pi),
    ("translation_error_nosym_mm", "translation_error_nosym_m", 1e3),
    ("rotation_error_nosym_deg", "rotation_error_nosym_rad", 180.0 / math.pi),
    ("pose_error_mm", "pose_error_m", 1e3),
    ("pose_error_nosym_mm", "pose_error_nosym_m", 1e3),
    ("add_mm", "add_m", 1e3),
    ("add_sym_mm", "add_sym_m", 1e3),
    ("adi_mm", "adi_m", 1e3),
    ("add_or_adi_mm", "add_or_adi_m", 1e3),
    ("mssd_mm", "mssd_m", 1e3),
    ("insertion_error_mm", "insertion_error_m", 1e3),
)
METRIC_NAMES = tuple(m[0] for m in _METRICS)


def _row(scores: dict[str, np.ndarray], i: int) -> dict[str, Any]:
    row: dict[str, Any] = {name: float(scores[key][i] * f) for name, key, f in _METRICS}
    ok = scores["insertable"][i]
    row["insertable"] = None if ok is None else bool(ok)
    row["symmetry_index"] = int(scores["symmetry_index"][i])
    return row


def _nees_block(value: float, bound: float) -> dict[str, Any]:
    return {"nees": float(value), "nees_bound": bound, "nees_within_bound": bool(value <= bound)}


BOP_NAME = re.compile(r"^[A-Za-z0-9]+(?:-[A-Za-z0-9]+)*_[A-Za-z0-9]+-[A-Za-z0-9]+(?:-[A-Za-z0-9]+)?$")


def bop_csv_name(name: str | None) -> str:
    """The BOP CSV's file name: ``estimates_bop.csv``, or ``NAME.csv`` for a BOP result name
    ``METHOD_DATASET-SPLIT[-SPLITTYPE]`` (bop_toolkit's scripts split the file name at the
    first ``_`` and the rest at ``-``: no ``_`` in the method, none in dataset or split)."""
    if name is None:
        return "estimates_bop.csv"
    stem = name[:-4] if name.endswith(".csv") else name
    if not BOP_NAME.match(stem):
        raise MvtopError(
            f"--bop-name {name!r}: expected METHOD_DATASET-SPLIT as bop_toolkit names results "
            "(e.g. mvtop_mydataset-test; letters, digits and '-' in the method, no '_' or '-' in dataset and split)"
        )
    return stem + ".csv"


def evaluate(track_dir: Path, log: Path | None, gt_file: Path | None, out_dir: Path, config: Config | None = None,
             bop_name: str | None = None) -> dict:
    """Score the track in ``track_dir`` against the ground truth of ``log`` (or the final
    pose in ``gt_file``, which wins when both are given) and write report.json,
    report.md, report.html and estimates_bop.csv into ``out_dir``; returns the report
    (the content of report.json).

    ``config`` defaults to ``track_dir/config.resolved.yaml``. ``bop_name`` names the BOP
    CSV as bop_toolkit expects results to be named (:func:`bop_csv_name`).
    """
    bop_file = bop_csv_name(bop_name)
    track_dir = Path(track_dir)
    track = read_track(track_dir)
    if config is None:
        cfg_path = track_dir / "config.resolved.yaml"
        if not cfg_path.is_file():
            raise TrackError(f"{cfg_path}: file not found (expected the resolved config written by mvtop estimate)")
        config = load_config(cfg_path)
    model = object_model(config)
    T_gt, gt_info = _ground_truth(track, log, gt_file, config)
    mspd = mspd_per_camera(model, track.T_world_object, T_gt, gt_info.pop("_cameras", {}))
    contact = gt_info.pop("_contact", None)
    n = len(track.stamps_ns)
    idx = np.flatnonzero(~np.isnan(T_gt).any(axis=(1, 2)))
    T_world_ee = track.T_world_ee
    # Per frame only the spreads are known: the diagonal approximation (docs/metrics.md).
    diag = np.zeros((n, 6, 6))
    diag[:, [0, 1, 2], [0, 1, 2]] = track.std_translation_m[:, None] ** 2
    diag[:, [3, 4, 5], [3, 4, 5]] = track.std_rotation_rad[:, None] ** 2
    scores = score_poses(model, track.T_world_object[idx], T_gt[idx], track.T_ee_object[idx], T_world_ee[idx],
                         diag[idx])
    final_scores = score_poses(model, track.T_world_object[-1:], T_gt[-1:], track.T_ee_object[-1:], T_world_ee[-1:],
                               track.final_covariance_ee[None])
    bound = M.chi2_bound(6, NEES_PROBABILITY)
    t0 = int(track.stamps_ns[0])

    def when(i: int) -> dict[str, Any]:
        return {
            "frame": int(track.frames[i]),
            "stamp_ns": int(track.stamps_ns[i]),
            "time_s": (int(track.stamps_ns[i]) - t0) * 1e-9,
        }

    per_frame = []
    for j, i in enumerate(idx):
        per_frame.append({
            **when(i), **_row(scores, j),
            "std_translation_mm": float(track.std_translation_m[i] * 1e3),
            "std_rotation_deg": float(np.degrees(track.std_rotation_rad[i])),
            **_nees_block(scores["nees"][j], bound),
            **({"mspd_px": {c: float(v[i]) for c, v in mspd.items()}} if mspd else {}),
        })
    final = {
        **when(n - 1), **_row(final_scores, 0),
        "clearance_mm": _mm(model.clearance_m),
        **_nees_block(final_scores["nees"][0], bound),
        **({"mspd_px": {c: float(v[-1]) for c, v in mspd.items()}} if mspd else {}),
        "nees_covariance": "summary.json final.covariance_ee (full 6x6)",
        "T_world_object_estimate": _pose_dict(track.T_world_object[-1]),
        "T_world_object_truth": _pose_dict(T_gt[-1]),
    }
    before = before_contact(contact, track.frames, idx, per_frame)
    frames_block: dict[str, Any] = {
        "count": n,
        "with_truth": int(len(idx)),
        **{name: _stats([r[name] for r in per_frame]) for name in METRIC_NAMES},
        "insertable_fraction": (None if model.clearance_m is None
                                else float(np.mean([r["insertable"] for r in per_frame]))),
        "nees": _stats(scores["nees"]),
        "nees_within_bound_fraction": float(np.mean(scores["nees"] <= bound)),
        "nees_covariance": "diagonal approximation from track.csv's std_translation_m and std_rotation_deg "
                           "(per-frame full covariances are not in track.csv)",
    }
    if mspd:
        frames_block["mspd_px"] = {c: _stats(v[idx]) for c, v in mspd.items()}
    summary_keys = ("log", "modalities", "particles", "seed", "frames_processed", "time_per_frame_s")
    report = _json_safe({
        "schema": REPORT_SCHEMA,
        "track_dir": str(track_dir),
        "object": model.name,
        "symmetries": int(len(model.group) - 1),
        "continuous_symmetry": _continuous_text(model),
        "clearance_mm": _mm(model.clearance_m),
        "insertion_depth_mm": model.insertion_depth_m * 1e3,
        "ground_truth": gt_info,
        "estimate": {k: track.summary.get(k) for k in summary_keys},
        "final": final,
        "before_contact": before,
        "frames": frames_block,
        "per_frame": per_frame,
        "files": {"bop_csv": bop_file, "markdown": "report.md", "html": "report.html"},
    })
    write_report(report, track, Path(out_dir))
    return report


def _ground_truth(track: Track, log: Path | None, gt_file: Path | None, config: Config) -> tuple[np.ndarray, dict]:
    """Truth ``T_world_object`` (N, 4, 4) per track frame (NaN where unknown) and where it came from."""
    n = len(track.stamps_ns)
    if gt_file is not None:
        T_gt = np.full((n, 4, 4), np.nan)
        T_gt[-1] = read_gt_file(Path(gt_file))
        return T_gt, {"source": "file", "file": str(gt_file), "frames": "final"}
    if log is None:
        raise MvtopError(
            "no ground truth: give the log with its ground-truth topic, or a --gt file with the final pose"
        )
    topic = config.topics.ground_truth
    tol = int(round(config.sync_tolerance_s * 1e9))
    T_gt, extra = ground_truth_from_log(Path(log), config, track.stamps_ns)
    if np.isnan(T_gt[-1]).any():
        raise LogError(
            f"{log}: ground truth on {topic!r} does not cover the final frame (stamp {int(track.stamps_ns[-1])} ns, "
            f"tolerance {tol} ns; its frame {extra['frame']!r} must connect to {config.frames.world!r} in TF then); "
            "expected the log the track was estimated from"
        )
    return T_gt, {"source": "log", "log": str(log), "topic": topic, "frame": extra["frame"], "frames": "all",
                  "interpolated": True, "_cameras": extra["cameras"], "_contact": extra["contact"]}


BEFORE_CONTACT_KEYS = ("frame", "insertion_error_mm", "translation_error_mm", "rotation_error_deg", "insertable")


def before_contact(contact: list[bool | None] | None, frames: np.ndarray, idx: np.ndarray,
                   per_frame: list[dict]) -> dict | None:
    """The errors at the last frame with ground truth before the log first reports contact
    (``contact`` and ``frames`` per track row; ``per_frame[j]`` scores row ``idx[j]``), with
    ``contact_frame`` that first contact frame: how well the part was held just before the
    receptacle acts on it.
    None when the log has no contact signal, never reports contact, or from its first frame."""
    onset = next((i for i, c in enumerate(contact or []) if c), None)
    scored = np.flatnonzero(idx < onset) if onset is not None else []
    if not len(scored):
        return None
    row = per_frame[scored[-1]]
    return {**{k: row[k] for k in BEFORE_CONTACT_KEYS}, "contact_frame": int(frames[onset])}


def _mm(value_m: float | None) -> float | None:
    return None if value_m is None else value_m * 1e3


def _pose_dict(T: np.ndarray) -> dict[str, list[float]]:
    return {"translation_m": [float(v) for v in T[:3, 3]], "quaternion_xyzw": [float(v) for v in se3.to_quat_xyzw(T)]}


def write_report(report: dict, track: Track, out_dir: Path) -> None:
    """report.json, report.md, report.html and the BOP CSV into ``out_dir``, each atomically."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise MvtopError(f"{out_dir}: cannot create the report folder ({err})") from None
    particles = track.summary.get("particles")
    ok = isinstance(particles, (int, float)) and particles > 0
    score = np.clip(track.ess / particles, 0.0, 1.0) if ok else np.ones(len(track.ess))
    time_s = track.summary.get("time_per_frame_s")
    time_s = float(time_s) if isinstance(time_s, (int, float)) else -1.0  # BOP: -1 means unknown
    with atomic_output(out_dir / report["files"]["bop_csv"], "w") as fh:
        fh.write(R.bop_csv(track.frames, track.T_world_object, score, time_s, scene_id=BOP_SCENE_ID, obj_id=BOP_OBJ_ID))
    with atomic_output(out_dir / "report.json", "w") as fh:
        json.dump(_json_safe(report), fh, indent=2, allow_nan=False)
        fh.write("\n")
    with atomic_output(out_dir / report["files"]["markdown"], "w") as fh:
        fh.write(R.render_markdown(report))
    with atomic_output(out_dir / report["files"]["html"], "w") as fh:
        fh.write(R.render_html(report))


def _json_safe(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# --- many runs ---------------------------------------------------------------------------------------


def aggregate(reports: list[dict]) -> dict:
    """Statistics of the final-frame metrics over runs: median, p95, mean and max of each
    metric, the success rate (fraction of runs whose final pose is insertable), the same just
    before contact (over the runs whose report has ``before_contact``), the mean final NEES and
    the fraction within its 95 % bound; overall and per object."""
    if not reports:
        raise MvtopError("aggregate: no reports given (expected at least one report.json)")
    finals = []
    for i, r in enumerate(reports):
        f = r.get("final") if isinstance(r, dict) else None
        if not isinstance(f, dict) or "insertable" not in f or "translation_error_mm" not in f:
            where = r.get("track_dir", f"report {i}") if isinstance(r, dict) else f"report {i}"
            raise MvtopError(
                f"{where}: final.insertable / final.translation_error_mm missing (expected an mvtop eval report)"
            )
        before = r.get("before_contact")
        finals.append((r.get("object", "?"), f, before if isinstance(before, dict) else None))

    def block(runs: list[tuple]) -> dict:
        items = [f for _o, f, _b in runs]
        out: dict[str, Any] = {"runs": len(items)}
        ok = [bool(f["insertable"]) for f in items if f["insertable"] is not None]  # None: no clearance configured
        out["successes"] = int(sum(ok)) if ok else None
        out["success_rate"] = float(np.mean(ok)) if ok else None
        held = [bool(b["insertable"]) for _o, _f, b in runs if b is not None and b.get("insertable") is not None]
        out["before_contact_runs"] = len(held)
        out["before_contact_success_rate"] = float(np.mean(held)) if held else None
        for name in METRIC_NAMES:
            vals = [f[name] for f in items if f.get(name) is not None]
            out[name] = _stats(vals)
        nees_vals = [f["nees"] for f in items if f.get("nees") is not None]
        out["nees"] = _stats(nees_vals)
        out["nees_within_bound_fraction"] = (
            float(np.mean([f["nees_within_bound"] for f in items if f.get("nees") is not None])) if nees_vals else None
        )
        return out

    result = block(finals)
    objects = sorted({o for o, _f, _b in finals})
    result["by_object"] = {o: block([x for x in finals if x[0] == o]) for o in objects}
    return result
