"""Inspect a log: topics, types, counts, rates, time range, and what a config needs but the log lacks."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..io import ros2_msgs as rm
from ..io.mcap_reader import LogSummary, McapLog
from ..io.urdf import UrdfKinematics


@dataclass(frozen=True)
class InspectReport:
    """What ``inspect_log`` found.

    ``wrong_types`` holds ``(topic, expected, actual)``; ``empty_topics`` required topics
    that exist but carry no message; ``tf_frames`` every frame named on a TFMessage
    topic (None when TF was not scanned); ``urdf_frames`` the links of the config's URDF
    (put into TF from the joint states when estimating); ``missing_frames`` required
    frames in neither. ``ground_truth``: with a ground-truth topic to check, its topic, the
    frame of its PoseStamped messages, the world frame and whether TF (with the URDF's links)
    connects the two (None: no such topic, or not a PoseStamped topic with messages).
    """

    summary: LogSummary
    required_topics: dict[str, str]
    missing_topics: tuple[str, ...]
    wrong_types: tuple[tuple[str, str, str], ...]
    empty_topics: tuple[str, ...]
    tf_frames: tuple[str, ...] | None
    required_frames: tuple[str, ...]
    missing_frames: tuple[str, ...]
    timing: dict[str, dict] = field(default_factory=dict)
    urdf_frames: tuple[str, ...] = ()
    ground_truth: GroundTruthFrame | None = None

    @property
    def ok(self) -> bool:
        """True when every requirement is met and the log is complete."""
        return not (
            self.missing_topics
            or self.wrong_types
            or self.empty_topics
            or self.missing_frames
            or self.summary.truncated_at is not None
            or (self.ground_truth is not None and not self.ground_truth.connected)
        )


@dataclass(frozen=True)
class GroundTruthFrame:
    """The frame of a log's ground-truth poses and whether TF connects it to the world."""

    topic: str
    frame: str
    world: str
    connected: bool

    def problem(self) -> str:
        """One line saying what is wrong (empty when the frame connects)."""
        if self.connected:
            return ""
        return (f"ground truth on {self.topic} is in frame {self.frame!r}, which TF does not connect to "
                f"{self.world!r} (expected its poses in {self.world!r}, or a frame on a TF chain to it)")


def _tf_edges(log: McapLog) -> set[tuple[str, str]]:
    """Every (parent, child) pair of any TFMessage topic."""
    tf_topics = [t.name for t in log.summary().topics if rm.normalize_type(t.type) == rm.TF_MESSAGE and t.message_count]
    edges: set[tuple[str, str]] = set()
    for m in log.messages(tf_topics) if tf_topics else ():
        for tr in m.msg.transforms:
            edges.add((str(tr.header.frame_id).lstrip("/"), str(tr.child_frame_id).lstrip("/")))
    return edges


def _connected(edges: set[tuple[str, str]], a: str, b: str) -> bool:
    """Whether a chain of transforms (either direction) joins frames ``a`` and ``b``."""
    links: dict[str, set[str]] = {}
    for p, c in edges:
        links.setdefault(p, set()).add(c)
        links.setdefault(c, set()).add(p)
    seen, todo = {a}, [a]
    while todo:
        for f in links.get(todo.pop(), ()):
            if f not in seen:
                seen.add(f)
                todo.append(f)
    return b in seen


def _ground_truth_frame(log: McapLog, topic: str | None) -> str | None:
    """The frame_id of the first PoseStamped on ``topic`` (None without one)."""
    summary = log.summary()
    if topic is None or not summary.has_topic(topic) or not summary.topic(topic).message_count:
        return None
    if rm.normalize_type(summary.topic(topic).type) != rm.normalize_type(rm.POSE_STAMPED):
        return None
    for m in log.messages([topic]):
        return str(m.msg.header.frame_id).lstrip("/")
    return None


def inspect_log(
    path: str | Path,
    required_topics: dict[str, str] | None = None,
    required_frames: list[str] | None = None,
    *,
    scan_tf: bool | None = None,
    urdf: str | Path | None = None,
    ground_truth_topic: str | None = None,
    world_frame: str = "world",
) -> InspectReport:
    """Summarise the log at ``path`` (an .mcap file or a rosbag2 folder) and check it against
    ``required_topics`` (topic -> ``pkg/msg/Name``) and ``required_frames`` (TF frame names).

    TF frames are collected (which reads every TF message) when ``scan_tf`` is True, or
    by default when ``required_frames`` is given. An interrupted recording (no footer)
    is read up to its last complete record and flagged rather than rejected; other
    unreadable logs raise LogError. With ``urdf`` (a robot model whose links come from
    the joint states), its links count as present frames.

    With ``ground_truth_topic`` (a PoseStamped topic; ignored when the log lacks it), the
    frame of its messages must be ``world_frame`` or joined to it by a chain of TF
    transforms (and the URDF's links), as ``estimate`` and ``eval`` convert it: checked on
    the TF tree of the whole log, not stamp by stamp.
    """
    urdf_frames: tuple[str, ...] = ()
    urdf_edges: set[tuple[str, str]] = set()
    if urdf is not None:
        kin = UrdfKinematics(urdf)
        urdf_frames = tuple(sorted({kin.root, *kin.links}))
        urdf_edges = {(kin.root, link) for link in kin.links}  # a URDF is one tree
    required_topics = dict(required_topics or {})
    required_frames = list(required_frames or [])
    with McapLog(path, allow_truncated=True) as log:
        summary = log.summary()
        missing, wrong, empty = [], [], []
        for topic, expected in required_topics.items():
            if not summary.has_topic(topic):
                missing.append(topic)
                continue
            info = summary.topic(topic)
            if expected and rm.normalize_type(info.type) != rm.normalize_type(expected):
                wrong.append((topic, rm.normalize_type(expected), info.type))
            elif info.message_count == 0:
                empty.append(topic)
        gt_frame = _ground_truth_frame(log, ground_truth_topic)
        do_tf = bool(required_frames) if scan_tf is None else scan_tf
        edges = _tf_edges(log) if do_tf or (gt_frame is not None and gt_frame != world_frame) else None
        frames = tuple(sorted({f for e in edges for f in e})) if do_tf and edges is not None else None
        image_topics = [
            t for t, e in required_topics.items()
            if rm.normalize_type(e or "") in (rm.IMAGE, rm.COMPRESSED_IMAGE) and t not in missing and t not in empty
            and not any(t == w[0] for w in wrong)
        ]
        timing = _image_timing(log, image_topics) if image_topics else {}
    ground_truth = None
    if gt_frame is not None:
        ok = gt_frame == world_frame or _connected((edges or set()) | urdf_edges, gt_frame, world_frame)
        ground_truth = GroundTruthFrame(str(ground_truth_topic), gt_frame, world_frame, ok)
    known = set(frames or ()) | set(urdf_frames)
    missing_frames = tuple(
        f for f in required_frames if (frames is None and not urdf_frames) or f.lstrip("/") not in known
    )
    return InspectReport(
        summary=summary,
        required_topics=required_topics,
        missing_topics=tuple(missing),
        wrong_types=tuple(wrong),
        empty_topics=tuple(empty),
        tf_frames=frames,
        required_frames=tuple(required_frames),
        missing_frames=missing_frames,
        timing=timing,
        urdf_frames=urdf_frames,
        ground_truth=ground_truth,
    )


def _image_timing(log: McapLog, topics: list[str]) -> dict[str, dict]:
    """Per image topic: rate [Hz], median period and largest gap [s], frames presumed dropped
    (gaps longer than 1.5 periods), and whether its rate differs from the fastest sensor's by
    more than 10 % (sensors at different rates are fine for the estimator, but worth knowing)."""
    times: dict[str, list[int]] = {t: [] for t in topics}
    for m in log.messages(topics, decode=False):
        times[m.topic].append(m.log_time_ns)
    out = {}
    for topic, ts in times.items():
        t = np.sort(np.asarray(ts, dtype=np.int64))
        if len(t) < 3:
            continue
        d = np.diff(t) * 1e-9
        period = float(np.median(d))
        dropped = int(np.sum(np.maximum(np.rint(d / period) - 1, 0))) if period > 0 else 0
        out[topic] = {"rate_hz": 1.0 / period if period > 0 else None, "period_s": period,
                      "max_gap_s": float(d.max()), "dropped": dropped}
    rates = [v["rate_hz"] for v in out.values() if v["rate_hz"]]
    for v in out.values():
        v["rate_mismatch"] = bool(rates and v["rate_hz"] and v["rate_hz"] < 0.9 * max(rates))
    return out


def _time(ns: int | None) -> str:
    if ns is None:
        return "-"
    # Logs stamped with wall-clock time read best as dates; simulated time (small
    # numbers) as seconds.
    if ns > 10**17:
        dt = datetime.fromtimestamp(ns // 1_000_000_000, tz=timezone.utc)
        return f"{dt:%Y-%m-%d %H:%M:%S}.{ns % 1_000_000_000:09d} UTC"
    return f"{ns * 1e-9:.9f} s"


def _table(header: list[str], rows: list[list[str]], right: set[int]) -> list[str]:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]

    def line(cells: list[str]) -> str:
        return "  ".join(
            c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths))
        ).rstrip()

    return [line(header), line(["-" * w for w in widths])] + [line(r) for r in rows]


def format_report(report: InspectReport) -> str:
    """The report as plain text: a header block, a topic table, then the requirement checks."""
    s = report.summary
    lines = [f"log:         {s.path}"]
    if len(s.files) > 1 or (s.files and s.files[0] != s.path):
        lines.append(f"files:       {len(s.files)} ({', '.join(f.name for f in s.files)})")
    lines += [
        f"profile:     {s.profile or '-'}  (written by {s.library or 'unknown'})",
        f"compression: {', '.join(s.compression) or '-'}"
        + (f" (chunks); {s.bag_compression} (rosbag2)" if s.bag_compression else "")
        + ("" if s.indexed else "  (no summary section: scanned)"),
        f"messages:    {s.message_count} on {len(s.topics)} topics",
        f"start:       {_time(s.start_ns)}",
        f"end:         {_time(s.end_ns)}",
        f"duration:    {s.duration_s:.3f} s",
    ]
    if s.truncated_at is not None:
        f, offset = s.truncated_at
        lines.append(f"WARNING:     {f.name} is truncated at byte {offset}; only complete records were read")
    lines.append("")
    need = report.required_topics
    rows = []
    for t in s.topics:
        rows.append(
            [
                t.name,
                t.type or "(no schema)",
                str(t.message_count),
                "-" if t.rate_hz is None else f"{t.rate_hz:.2f}",
                "-" if t.first_ns is None or t.last_ns is None else f"{(t.last_ns - t.first_ns) * 1e-9:.3f}",
                "required" if t.name in need else "",
            ]
        )
    for topic in report.missing_topics:
        rows.append([topic, rm.normalize_type(need[topic]) if need[topic] else "?", "-", "-", "-", "MISSING"])
    for topic, expected, _actual in report.wrong_types:
        row = next(r for r in rows if r[0] == topic)
        row[5] = f"WRONG TYPE (expected {expected})"
    for topic in report.empty_topics:
        row = next(r for r in rows if r[0] == topic)
        row[5] = "EMPTY"
    lines += _table(["topic", "type", "count", "rate Hz", "span s", "check"], rows, right={2, 3, 4})
    if report.tf_frames is not None:
        lines += ["", f"TF frames:   {', '.join(report.tf_frames) or '(none)'}"]
    if report.urdf_frames:
        lines += [f"URDF links:  {', '.join(report.urdf_frames)} (from the joint states)"]
    gt = report.ground_truth
    if gt is not None:
        how = ("" if gt.frame == gt.world else " (converted through TF)") if gt.connected else \
            f" (NOT CONNECTED to {gt.world!r} through TF)"
        lines += [f"ground truth: {gt.topic} in frame {gt.frame!r}{how}"]
    if report.timing:
        rows = []
        for topic, v in report.timing.items():
            notes = []
            if v["dropped"]:
                notes.append(f"{v['dropped']} dropped (gap up to {v['max_gap_s']:.3f} s)")
            if v["rate_mismatch"]:
                notes.append("slower than the fastest sensor")
            rows.append([topic, "-" if not v["rate_hz"] else f"{v['rate_hz']:.2f}", f"{v['max_gap_s']:.3f}",
                         "; ".join(notes) or "ok"])
        lines += ["", "image timing (frames are formed from whatever arrives; these are notes, not errors):"]
        lines += _table(["topic", "rate Hz", "max gap s", "note"], rows, right={1, 2})
    if need or report.required_frames:
        lines.append("")
        problems = []
        if report.missing_topics:
            problems.append(f"missing topics: {', '.join(report.missing_topics)}")
        if report.wrong_types:
            problems.append(
                "wrong types: " + ", ".join(f"{t} is {a} (expected {e})" for t, e, a in report.wrong_types)
            )
        if report.empty_topics:
            problems.append(f"topics without messages: {', '.join(report.empty_topics)}")
        if report.missing_frames:
            problems.append(f"missing TF frames: {', '.join(report.missing_frames)}")
        if s.truncated_at is not None:
            problems.append("the log is truncated")
        if gt is not None and not gt.connected:
            problems.append(gt.problem())
        if problems:
            lines += ["PROBLEMS:"] + [f"  - {p}" for p in problems]
        else:
            lines.append("OK: every required topic and TF frame is present."
                         + (" The ground truth's frame connects to the world." if gt is not None else ""))
    return "\n".join(lines)
