"""A TF buffer over a whole log: look up ``T_target_source`` at any time through the frame tree.

Built from tf2_msgs/TFMessage messages (``/tf_static`` and ``/tf``). Each edge
``parent -> child`` is either static (one pose) or dynamic (a time series kept as numpy
arrays: int64 stamps [ns], (n, 3) translations [m], (n, 4) quaternions (x, y, z, w)).
Dynamic edges are interpolated in time (linear translation, slerp rotation); outside the
sampled interval a lookup fails unless it is within ``extrapolation_tolerance_ns`` of an
end, where the end pose is held.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import LogError
from ..geometry import se3


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (``sec``, ``nanosec``) -> int nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _strip(frame: str) -> str:
    # tf2 ignores a leading slash (a ROS 1 habit); so do we.
    return str(frame).lstrip("/")


class PoseSeries:
    """A time series of poses with interpolation: stamps (n,) int64 [ns], sorted."""

    def __init__(self, stamps_ns: np.ndarray, translations: np.ndarray, quats_xyzw: np.ndarray):
        order = np.argsort(stamps_ns, kind="stable")
        t = np.asarray(stamps_ns, dtype=np.int64)[order]
        p = np.asarray(translations, dtype=np.float64).reshape(-1, 3)[order]
        q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)[order]
        # Keep the last sample of duplicated stamps (a re-published transform replaces the old).
        keep = np.ones(len(t), dtype=bool)
        keep[:-1] = t[1:] != t[:-1]
        self.stamps_ns = t[keep]
        self.translations = p[keep]
        self.quats_xyzw = q[keep]

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def start_ns(self) -> int:
        return int(self.stamps_ns[0])

    @property
    def end_ns(self) -> int:
        return int(self.stamps_ns[-1])

    def _pose(self, i: int) -> np.ndarray:
        return se3.from_quat_xyzw(self.quats_xyzw[i], self.translations[i])

    def covers(self, t_ns: int, tolerance_ns: int = 0) -> bool:
        return self.start_ns - tolerance_ns <= t_ns <= self.end_ns + tolerance_ns

    def at(self, t_ns: int) -> np.ndarray:
        """Pose (4, 4) at ``t_ns``: interpolated inside the samples, the end pose outside."""
        t = self.stamps_ns
        i = int(np.searchsorted(t, t_ns, side="right"))
        if i == 0:
            return self._pose(0)
        if i == len(t):
            return self._pose(len(t) - 1)
        t0, t1 = int(t[i - 1]), int(t[i])
        if t_ns == t0:
            return self._pose(i - 1)
        alpha = (t_ns - t0) / (t1 - t0)
        return se3.interpolate(self._pose(i - 1), self._pose(i), alpha)


@dataclass
class _Edge:
    parent: str
    static: np.ndarray | None = None  # (4, 4) T_parent_child
    series: PoseSeries | None = None
    # growing buffers while the buffer is being filled (compact typed arrays, not lists)
    _t: array | None = None
    _v: array | None = None


class TfBuffer:
    """Transforms between named frames over the time span of a log.

    ``source`` names the log in error messages. Fill with ``add_static`` /
    ``add_dynamic`` / ``add_tf_message``; lookups finalize the buffer (later additions
    are still allowed and re-finalize).
    """

    def __init__(self, extrapolation_tolerance_ns: int = 0, source: str = "TF"):
        if extrapolation_tolerance_ns < 0:
            raise ValueError("extrapolation_tolerance_ns must be >= 0")
        self.tolerance_ns = int(extrapolation_tolerance_ns)
        self.source = source
        self._edges: dict[str, _Edge] = {}  # keyed by child frame
        self._dirty = False

    # --- filling ------------------------------------------------------------------------

    def _edge(self, parent: str, child: str, static: bool) -> _Edge:
        if parent == child:
            raise LogError(
                f"{self.source}: transform from frame {child!r} to itself "
                "(expected a child frame other than its parent)"
            )
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent=parent)
        elif edge.parent != parent:
            raise LogError(
                f"{self.source}: frame {child!r} has two parents, {edge.parent!r} and {parent!r} "
                "(expected a tree: one parent per frame)"
            )
        is_dynamic = edge._t is not None or edge.series is not None
        if (static and is_dynamic) or (not static and edge.static is not None):
            raise LogError(
                f"{self.source}: transform {parent!r} -> {child!r} is published both as static and "
                "as dynamic (expected each edge on only one of /tf_static and /tf)"
            )
        return edge

    def add_static(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        """Add (or replace) a static edge; ``T_parent_child`` is (4, 4)."""
        parent, child = _strip(parent), _strip(child)
        edge = self._edge(parent, child, static=True)
        edge.static = np.array(T_parent_child, dtype=np.float64)

    def add_dynamic(
        self, parent: str, child: str, stamp_ns: int, translation: Iterable[float], quat_xyzw: Iterable[float]
    ) -> None:
        """Add one sample of a dynamic edge: translation (3,) [m], quaternion (4,) (x, y, z, w)."""
        parent, child = _strip(parent), _strip(child)
        t, q = valid_transform(translation, quat_xyzw, self.source, f"transform {parent!r} -> {child!r}")
        edge = self._edge(parent, child, static=False)
        if edge._t is None:
            edge._t, edge._v = array("q"), array("d")
        edge._t.append(int(stamp_ns))
        edge._v.extend(t)
        edge._v.extend(q)
        self._dirty = True

    def add_tf_message(self, msg: Any, static: bool) -> None:
        """Add every transform of a decoded tf2_msgs/TFMessage."""
        for tr in msg.transforms:
            tt, rr = tr.transform.translation, tr.transform.rotation
            t = (tt.x, tt.y, tt.z)
            q = (rr.x, rr.y, rr.z, rr.w)
            if static:
                t, q = valid_transform(t, q, self.source, f"transform {tr.header.frame_id!r} -> {tr.child_frame_id!r}")
                self.add_static(tr.header.frame_id, tr.child_frame_id, se3.from_quat_xyzw(q, t))
            else:
                self.add_dynamic(tr.header.frame_id, tr.child_frame_id, stamp_to_ns(tr.header.stamp), t, q)

    def _finalize(self) -> None:
        if not self._dirty:
            return
        for edge in self._edges.values():
            if edge._t is None:
                continue
            t_new = np.frombuffer(edge._t, dtype=np.int64)
            v_new = np.frombuffer(edge._v, dtype=np.float64).reshape(-1, 7)
            if edge.series is not None:
                t_new = np.concatenate([edge.series.stamps_ns, t_new])
                v_new = np.concatenate(
                    [np.hstack([edge.series.translations, edge.series.quats_xyzw]), v_new]
                )
            edge.series = PoseSeries(t_new, v_new[:, :3], v_new[:, 3:])
            edge._t = edge._v = None
        self._dirty = False

    # --- queries ------------------------------------------------------------------------

    @property
    def frames(self) -> set[str]:
        """Every frame named as a parent or a child."""
        out = set(self._edges)
        out.update(e.parent for e in self._edges.values())
        return out

    def parent(self, frame: str) -> str | None:
        edge = self._edges.get(_strip(frame))
        return None if edge is None else edge.parent

    def is_static(self, parent: str, child: str) -> bool:
        edge = self._edges.get(_strip(child))
        return edge is not None and edge.parent == _strip(parent) and edge.static is not None

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        chain = [frame]
        while frame in self._edges:
            frame = self._edges[frame].parent
            if frame in chain:
                raise LogError(f"{self.source}: the TF tree has a loop through frame {frame!r} (expected a tree)")
            chain.append(frame)
        return chain

    def _path(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """Frames from ``source`` and from ``target`` up to (excluding) their common ancestor."""
        known = self.frames
        for name in (target, source):
            if name not in known:
                listed = ", ".join(sorted(known)) or "none"
                raise LogError(f"{self.source}: frame {name!r} is not in the TF tree (known frames: {listed})")
        up_s, up_t = self._chain(source), self._chain(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            raise LogError(
                f"{self.source}: frames {target!r} and {source!r} are not connected in the TF tree "
                f"(their roots are {up_t[-1]!r} and {up_s[-1]!r})"
            )
        return up_s[: up_s.index(common)], up_t[: up_t.index(common)]

    def time_bounds(self, target: str, source: str) -> tuple[float, float]:
        """Interval [ns] in which ``lookup(target, source, t)`` succeeds, tolerance included
        (``(-inf, inf)`` when every edge on the path is static)."""
        self._finalize()
        target, source = _strip(target), _strip(source)
        lo, hi = -np.inf, np.inf
        for child in sum(self._path(target, source), []):
            series = self._edges[child].series
            if series is not None:
                lo = max(lo, series.start_ns - self.tolerance_ns)
                hi = min(hi, series.end_ns + self.tolerance_ns)
        return lo, hi

    def _edge_pose(self, child: str, t_ns: int) -> np.ndarray:
        edge = self._edges[child]
        if edge.static is not None:
            return edge.static
        series = edge.series
        assert series is not None
        if not series.covers(t_ns, self.tolerance_ns):
            raise LogError(
                f"{self.source}: transform {edge.parent!r} -> {child!r} is not available at t={t_ns} ns "
                f"(data covers {series.start_ns}..{series.end_ns} ns, extrapolation tolerance "
                f"{self.tolerance_ns} ns)"
            )
        return series.at(t_ns)

    def lookup(self, target: str, source: str, t_ns: int) -> np.ndarray:
        """``T_target_source`` (4, 4) at time ``t_ns``: maps points in ``source`` to ``target``.

        Raises LogError when a frame is unknown, the two frames are not connected, or a
        dynamic edge on the path has no data at ``t_ns`` (beyond the tolerance).
        """
        self._finalize()
        target, source = _strip(target), _strip(source)
        up_s, up_t = self._path(target, source)
        T_anc_source = np.eye(4)
        for child in reversed(up_s):  # from the common ancestor down to source
            T_anc_source = T_anc_source @ self._edge_pose(child, t_ns)
        T_anc_target = np.eye(4)
        for child in reversed(up_t):
            T_anc_target = T_anc_target @ self._edge_pose(child, t_ns)
        return se3.invert(T_anc_target) @ T_anc_source


# Largest translation component accepted [m]: far beyond any robot cell, small enough that
# poses composed from a few of them stay finite in float64 arithmetic.
MAX_TRANSLATION_M = 1e6


def valid_transform(
    translation: Iterable[float], quat_xyzw: Iterable[float], source: str, what: str
) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """``(translation (3,) [m], unit quaternion (x, y, z, w))`` of a transform read from a log.

    Raises LogError naming ``source`` and ``what`` (e.g. ``"transform 'world' -> 'ee'"``)
    when the translation is not finite or beyond ``MAX_TRANSLATION_M``, or the quaternion
    is not finite or has a norm far from 1 (below 1e-3 or above 1e3; anything closer is
    normalised, as tf2 does with slightly denormalised quaternions).
    """
    t = np.asarray(tuple(translation), dtype=np.float64)
    if t.shape != (3,) or not np.all(np.isfinite(t)) or np.any(np.abs(t) > MAX_TRANSLATION_M):
        raise LogError(
            f"{source}: {what} has an invalid translation {t.tolist()} "
            f"(expected three finite numbers within +-{MAX_TRANSLATION_M:g} m)"
        )
    v = np.asarray(tuple(quat_xyzw), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # inf / huge values are reported below
        n = float(np.sqrt(np.sum(np.square(v)))) if v.shape == (4,) else float("nan")
    if not np.isfinite(n) or not 1e-3 <= n <= 1e3:
        raise LogError(
            f"{source}: {what} has an invalid quaternion {v.tolist()} "
            "(expected a finite (x, y, z, w) of norm 1)"
        )
    v = v / n
    return (float(t[0]), float(t[1]), float(t[2])), (float(v[0]), float(v[1]), float(v[2]), float(v[3]))
