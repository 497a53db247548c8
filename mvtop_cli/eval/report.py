"""Render an evaluation report: Markdown tables, a self-contained HTML page with inline
SVG plots (log-scale error over time), and the BOP results CSV. Text in, text out."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence

import numpy as np

BOP_HEADER = "scene_id,im_id,obj_id,score,R,t,time"

# (report key, label, unit) of the rows shown in the tables, in order.
TABLE_ROWS = (
    ("translation_error_mm", "translation error", "mm"),
    ("rotation_error_deg", "rotation error", "deg"),
    ("pose_error_mm", "pose error (mean bbox-corner distance, paper)", "mm"),
    ("add_mm", "ADD", "mm"),
    ("adi_mm", "ADD-S (BOP adi)", "mm"),
    ("add_sym_mm", "ADD, min over symmetries", "mm"),
    ("mssd_mm", "MSSD", "mm"),
    ("insertion_error_mm", "insertion error (max lateral corner displacement)", "mm"),
    ("translation_error_nosym_mm", "translation error, ignoring symmetries", "mm"),
    ("rotation_error_nosym_deg", "rotation error, ignoring symmetries", "deg"),
)


def bop_csv(
    frames: Sequence[int],
    T_world_object: np.ndarray,
    scores: Sequence[float],
    time_s: float,
    scene_id: int = 0,
    obj_id: int = 1,
) -> str:
    """BOP results CSV (bop_toolkit ``inout.save_bop_results``): one line per frame,
    ``scene_id,im_id,obj_id,score,R,t,time`` with ``R`` the 9 rotation entries row-major
    and ``t`` the translation [mm], space-separated, ``time`` [s] per image (-1 unknown).

    BOP poses are model-to-camera; mvtop has no single camera, so these are
    model-to-world (``T_world_object``): every pose-only BOP error (MSSD, ADD, te, re) is
    unchanged when truth and estimate share the frame.
    """
    T = np.asarray(T_world_object, dtype=np.float64).reshape(-1, 4, 4)
    lines = [BOP_HEADER]
    for im_id, Ti, score in zip(frames, T, scores):
        R = " ".join(repr(float(v)) for v in Ti[:3, :3].reshape(-1))
        t = " ".join(repr(float(v) * 1000.0) for v in Ti[:3, 3])
        lines.append(f"{int(scene_id)},{int(im_id)},{int(obj_id)},{float(score)!r},{R},{t},{float(time_s)!r}")
    return "\n".join(lines) + "\n"


def parse_bop_csv(text: str) -> list[dict]:
    """Rows of a BOP results CSV: dicts with ``scene_id, im_id, obj_id`` (int), ``score,
    time`` (float), ``R`` (3, 3) and ``t`` (3,) [mm]."""
    lines = [l for l in text.splitlines() if l.strip()]
    if not lines or lines[0].strip() != BOP_HEADER:
        raise ValueError(f"expected the header {BOP_HEADER!r}")
    rows = []
    for line in lines[1:]:
        scene, im, obj, score, R, t, time = line.split(",")
        rows.append({
            "scene_id": int(scene), "im_id": int(im), "obj_id": int(obj), "score": float(score),
            "R": np.array([float(v) for v in R.split()]).reshape(3, 3), "t": np.array([float(v) for v in t.split()]),
            "time": float(time),
        })
    return rows


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    if not math.isfinite(v):
        return "–"
    if v != 0 and (abs(v) < 10 ** -digits or abs(v) >= 1e6):
        return f"{v:.{digits}g}"
    return f"{v:.{digits}f}"


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


_SYMMETRY_ONLY = ("add_sym_mm", "translation_error_nosym_mm", "rotation_error_nosym_deg")


def _table_rows(report: dict) -> tuple[tuple[str, str, str], ...]:
    """TABLE_ROWS without the rows that repeat others when the object has no symmetries."""
    if report.get("symmetries") or report.get("continuous_symmetry"):
        return TABLE_ROWS
    return tuple(r for r in TABLE_ROWS if r[0] not in _SYMMETRY_ONLY)


def _final_rows(report: dict) -> list[list[str]]:
    f = report["final"]
    rows = [[label, _fmt(f.get(key)), unit] for key, label, unit in _table_rows(report)]
    rows += [[f"MSPD, camera {cam}", _fmt(v), "px"] for cam, v in (f.get("mspd_px") or {}).items()]
    rows.append(["clearance (per side)", _fmt(f.get("clearance_mm")), "mm"])
    ins = f.get("insertable")
    verdict = "n/a (no clearance configured)" if ins is None else _fmt(bool(ins))
    rows.append(["**insertable**", f"**{verdict}**", ""])
    rows.append(["NEES (full covariance)", _fmt(f.get("nees")), f"95 % bound {_fmt(f.get('nees_bound'), 2)}"])
    rows.append(["NEES within bound", _fmt(bool(f.get("nees_within_bound"))), ""])
    return rows


def _frame_rows(report: dict) -> list[list[str]]:
    fr = report["frames"]
    rows = []
    for key, label, unit in _table_rows(report):
        s = fr.get(key) or {}
        rows.append([label, unit, _fmt(s.get("median")), _fmt(s.get("p95")), _fmt(s.get("max"))])
    s = fr.get("nees") or {}
    rows.append(["NEES (diagonal approx.)", "", _fmt(s.get("median")), _fmt(s.get("p95")), _fmt(s.get("max"))])
    return rows


_PER_FRAME_COLUMNS = (
    ("frame", "frame"), ("time_s", "t [s]"), ("translation_error_mm", "trans. [mm]"),
    ("rotation_error_deg", "rot. [deg]"), ("pose_error_mm", "pose err. [mm]"), ("insertion_error_mm", "insert. [mm]"),
    ("insertable", "insertable"), ("std_translation_mm", "σt [mm]"), ("std_rotation_deg", "σr [deg]"), ("nees", "NEES"),
)
MAX_TABLE_FRAMES = 200


def _per_frame_table(report: dict) -> tuple[list[str], list[list[str]], str]:
    rows = report["per_frame"]
    note = ""
    if len(rows) > MAX_TABLE_FRAMES:
        step = math.ceil(len(rows) / MAX_TABLE_FRAMES)
        rows = rows[::step]
        note = f"Every {step}th frame shown; report.json has all {len(report['per_frame'])}."
    body = [[_fmt(r.get(k), 2 if k == "time_s" else 3) for k, _ in _PER_FRAME_COLUMNS] for r in rows]
    return [h for _, h in _PER_FRAME_COLUMNS], body, note


def render_markdown(report: dict) -> str:
    """report.md: inputs, the final frame, per-frame aggregates and the per-frame table."""
    fr = report["frames"]
    gt = report["ground_truth"]
    src = (f"log `{gt.get('log')}`, topic `{gt.get('topic')}`" if gt["source"] == "log"
           else f"file `{gt.get('file')}` (final frame only)")
    parts = [
        f"# mvtop evaluation: {report['object']}",
        "",
        f"- track: `{report['track_dir']}`",
        f"- ground truth: {src}",
        f"- frames: {fr['count']} estimated, {fr['with_truth']} with ground truth",
        f"- symmetries: {report['symmetries']} besides the identity"
        + (f", and {report['continuous_symmetry']}" if report.get("continuous_symmetry") else "")
        + f"; clearance {_fmt(report['clearance_mm'])} mm per side, "
        f"insertion depth {_fmt(report['insertion_depth_mm'])} mm",
        "",
        f"## Final frame (frame {report['final']['frame']})",
        "",
        _md_table(["metric", "value", "unit"], _final_rows(report)),
        "",
        "## Over frames",
        "",
        _md_table(["metric", "unit", "median", "p95", "max"], _frame_rows(report)),
        "",
        (f"Insertable in {_fmt(100 * fr['insertable_fraction'], 1)} % of frames; "
         if fr["insertable_fraction"] is not None else "Insertable: n/a (no clearance configured); ")
        + f"NEES within the 95 % chi-square bound "
        f"({_fmt(report['final']['nees_bound'], 2)}, 6 dof) "
        f"in {_fmt(100 * fr['nees_within_bound_fraction'], 1)} % of frames. "
        f"Per-frame NEES uses a {fr['nees_covariance']}.",
        "",
        "## Per frame",
        "",
    ]
    header, body, note = _per_frame_table(report)
    parts.append(_md_table(header, body))
    if note:
        parts += ["", note]
    parts += [
        "",
        "Definitions: docs/metrics.md. Errors use the symmetric equivalent of the estimate closest to the truth.",
        "",
    ]
    return "\n".join(parts)


# --- SVG --------------------------------------------------------------------------------------------

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


class _LogAxis:
    """A logarithmic y axis spanning whole decades around the positive ``values``. Values
    <= 0 (a perfect estimate has no logarithm) are drawn on the bottom edge, a decade below
    the smallest positive value, labelled "<=" (``has_zero``)."""

    def __init__(self, values: np.ndarray, has_zero: bool) -> None:
        pos = np.asarray(values, dtype=np.float64)
        if len(pos) == 0:
            pos = np.array([1e-3, 1.0])
        self.lo_dec = math.floor(math.log10(pos.min())) - (1 if has_zero else 0)
        self.hi_dec = max(math.ceil(math.log10(pos.max())), self.lo_dec + 1)
        self.has_zero = has_zero
        self.floor = 10.0 ** self.lo_dec

    def y(self, v: float, top: float, plot_height: float) -> float:
        """Pixel row of value ``v`` in a plot area starting at row ``top``."""
        v = max(v, self.floor) if math.isfinite(v) else self.floor
        return top + (self.hi_dec - math.log10(v)) / (self.hi_dec - self.lo_dec) * plot_height

    def frame(self, width: int, height: int, ml: float, mt: float, pw: float, ph: float, title: str) -> list[str]:
        """The SVG's opening tags: title, plot frame, decade grid lines and labels, minor ticks."""
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
               f'viewBox="0 0 {width} {height}" '
               'font-family="sans-serif" font-size="11">',
               f'<text x="{ml}" y="16" font-size="13" font-weight="bold">{html.escape(title)}</text>',
               f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" fill="none" stroke="#444"/>']
        for d in range(self.lo_dec, self.hi_dec + 1):
            y = self.y(10.0 ** d, mt, ph)
            out.append(f'<line x1="{ml}" x2="{ml + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#ddd"/>')
            le = "≤" if self.has_zero and d == self.lo_dec else ""
            out.append(f'<text x="{ml - 6}" y="{y + 4:.1f}" text-anchor="end">{le}1e{d}</text>')
            for m in range(2, 10):
                if d < self.hi_dec:
                    ym = self.y(m * 10.0 ** d, mt, ph)
                    out.append(f'<line x1="{ml}" x2="{ml + 4}" y1="{ym:.1f}" y2="{ym:.1f}" stroke="#999"/>')
        return out


def svg_log_plot(
    x: Sequence[float],
    series: Sequence[tuple[str, Sequence[float | None], bool]],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    hlines: Sequence[tuple[str, float]] = (),
    width: int = 720,
    height: int = 300,
) -> str:
    """An inline SVG line plot with a logarithmic y axis.

    ``series`` are ``(label, values, dashed)``; values <= 0 or None are drawn at the
    bottom of the axis (a perfect estimate has no logarithm). ``hlines`` are labelled
    horizontal reference lines (e.g. the clearance).
    """
    xs = np.asarray(x, dtype=np.float64)
    vals = [np.array([np.nan if v is None else float(v) for v in s], dtype=np.float64) for _, s, _ in series]
    pos = np.concatenate([v[np.isfinite(v) & (v > 0)] for v in vals] + [np.array([h for _, h in hlines if h > 0])])
    axis = _LogAxis(pos, any(np.any(np.isfinite(v) & (v <= 0)) for v in vals))
    ml, mr, mt, mb = 64, 170, 28, 42
    pw, ph = width - ml - mr, height - mt - mb
    x0, x1 = (float(xs.min()), float(xs.max())) if len(xs) else (0.0, 1.0)
    if x1 <= x0:
        x0, x1 = x0 - 0.5, x0 + 0.5

    def px(v: float) -> float:
        return ml + (v - x0) / (x1 - x0) * pw

    def py(v: float) -> float:
        return axis.y(v, mt, ph)

    out = axis.frame(width, height, ml, mt, pw, ph, title)
    for t in np.linspace(x0, x1, 6):
        out.append(f'<line x1="{px(t):.1f}" x2="{px(t):.1f}" y1="{mt + ph}" y2="{mt + ph + 4}" stroke="#444"/>')
        out.append(f'<text x="{px(t):.1f}" y="{mt + ph + 16}" text-anchor="middle">{t:.3g}</text>')
    out.append(f'<text x="{ml + pw / 2}" y="{height - 6}" text-anchor="middle">{html.escape(xlabel)}</text>')
    out.append(f'<text x="14" y="{mt + ph / 2}" text-anchor="middle" transform="rotate(-90 14 {mt + ph / 2})">'
               f'{html.escape(ylabel)} (log scale)</text>')
    legend_y = mt + 8
    for k, ((label, _, dashed), v) in enumerate(zip(series, vals)):
        color = _COLORS[k % len(_COLORS)]
        dash = ' stroke-dasharray="5,3"' if dashed else ""
        pts = " ".join(f"{px(a):.1f},{py(b):.1f}" for a, b in zip(xs, v) if not np.isnan(b))
        if pts:
            out.append(f'<polyline fill="none" stroke="{color}" stroke-width="1.6"{dash} points="{pts}"/>')
            for a, b in zip(xs, v):
                if not np.isnan(b):
                    out.append(f'<circle cx="{px(a):.1f}" cy="{py(b):.1f}" r="2" fill="{color}"/>')
        out.append(f'<line x1="{ml + pw + 10}" x2="{ml + pw + 30}" y1="{legend_y}" y2="{legend_y}" stroke="{color}" '
                   f'stroke-width="2"{dash}/>')
        out.append(f'<text x="{ml + pw + 34}" y="{legend_y + 4}">{html.escape(label)}</text>')
        legend_y += 16
    for label, h in hlines:
        y = py(h)
        out.append(f'<line x1="{ml}" x2="{ml + pw}" y1="{y:.1f}" y2="{y:.1f}" stroke="#000" stroke-dasharray="2,2"/>')
        out.append(f'<text x="{ml + pw + 10}" y="{legend_y + 4}">··· {html.escape(label)}</text>')
        legend_y += 16
    out.append("</svg>")
    return "\n".join(out)


REPORT_CSS = """body{font-family:sans-serif;margin:2em;max-width:60em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
td:first-child,th:first-child{text-align:left}th{background:#f3f3f3}.ok{color:#186a18}.bad{color:#a11}"""


def html_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in header)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(c.replace('**', ''))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


def render_html(report: dict) -> str:
    """report.html: one self-contained page (inline CSS and SVG, no scripts, no links)."""
    f = report["final"]
    pf = report["per_frame"]
    t = [r["time_s"] for r in pf]
    dist = svg_log_plot(
        t,
        [("translation error", [r["translation_error_mm"] for r in pf], False),
         ("pose error (bbox)", [r["pose_error_mm"] for r in pf], False),
         ("insertion error", [r["insertion_error_mm"] for r in pf], False),
         ("σ translation", [r["std_translation_mm"] for r in pf], True)],
        title="Distance errors over time", xlabel="time since first frame [s]", ylabel="error [mm]",
        hlines=([(f"clearance {_fmt(report['clearance_mm'])} mm", report["clearance_mm"])]
                if report["clearance_mm"] is not None else []),
    )
    rot = svg_log_plot(
        t,
        [("rotation error", [r["rotation_error_deg"] for r in pf], False),
         ("σ rotation", [r["std_rotation_deg"] for r in pf], True)],
        title="Rotation error over time", xlabel="time since first frame [s]", ylabel="error [deg]",
    )
    nees = svg_log_plot(
        t, [("NEES (diag. cov.)", [r["nees"] for r in pf], False)],
        title="NEES over time", xlabel="time since first frame [s]", ylabel="NEES",
        hlines=[(f"95 % bound {_fmt(f['nees_bound'], 2)}", f["nees_bound"])],
    )
    verdict = ("insertable: n/a (no clearance configured)" if f["insertable"] is None else
               '<span class="ok">insertable</span>' if f["insertable"] else '<span class="bad">not insertable</span>')
    header, body, note = _per_frame_table(report)
    fr = report["frames"]
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>mvtop evaluation: {html.escape(report['object'])}</title>",
        f"<style>{REPORT_CSS}</style></head><body>",
        f"<h1>mvtop evaluation: {html.escape(report['object'])}</h1>",
        f"<p>Track <code>{html.escape(report['track_dir'])}</code>; ground truth from the "
        f"{html.escape(report['ground_truth']['source'])}; {fr['count']} frames, {fr['with_truth']} with ground truth. "
        f"Final frame: {verdict} (insertion error {_fmt(f['insertion_error_mm'])} mm, clearance "
        f"{_fmt(report['clearance_mm'])} mm).</p>",
        f"<h2>Final frame (frame {f['frame']})</h2>",
        html_table(["metric", "value", "unit"], _final_rows(report)),
        "<h2>Error over time</h2>",
        dist, rot, nees,
        "<h2>Over frames</h2>",
        html_table(["metric", "unit", "median", "p95", "max"], _frame_rows(report)),
        f"<p>Per-frame NEES uses a {html.escape(fr['nees_covariance'])}.</p>",
        "<h2>Per frame</h2>",
        html_table(header, body),
        f"<p>{html.escape(note)}</p>" if note else "",
        "<p>Definitions: docs/metrics.md in the mvtop repository.</p>",
        "</body></html>",
        "",
    ])


def svg_log_boxplot(
    groups: Sequence[str],
    series: Sequence[tuple[str, Sequence[Sequence[float]]]],
    *,
    title: str,
    ylabel: str,
    height: int = 320,
) -> str:
    """An inline SVG box plot with a logarithmic y axis (as the M-VTOP paper's figure 4).

    ``groups`` label the x axis (e.g. objects); ``series`` are ``(label, values)`` with one
    sequence of values per group (e.g. one method's errors per object), drawn as side-by-side
    boxes in the series' colour; a group with no values gets no box. A box spans the
    quartiles, its line is the median, the whiskers reach the most extreme values within 1.5
    interquartile ranges of the box and the values beyond are dots. Values <= 0 are drawn on
    the bottom edge, as in :func:`svg_log_plot`. Each box is a ``<g class="box">`` with
    ``data-group``, ``data-series``, ``data-n`` and ``data-median`` (``repr`` of the median)
    and a tooltip.
    """
    vals = [[np.array([v for v in g if v is not None and math.isfinite(v)], dtype=np.float64) for g in s]
            for _, s in series]
    allv = np.concatenate([v for s in vals for v in s] + [np.zeros(0)])
    axis = _LogAxis(allv[allv > 0], bool(np.any(allv <= 0)))
    ns = max(1, len(series))
    box_w = 18
    ml, mr, mt, mb = 64, 150, 28, 48
    # at least room for the title; wider groups spread the boxes apart
    group_w = max(ns * box_w + 26, 360 / max(len(groups), 1))
    gap = group_w - ns * box_w
    pw = max(len(groups), 1) * group_w
    width = int(math.ceil(ml + pw + mr))
    ph = height - mt - mb

    def py(v: float) -> float:
        return axis.y(v, mt, ph)

    out = axis.frame(width, height, ml, mt, pw, ph, title)
    out.append(f'<text x="14" y="{mt + ph / 2}" text-anchor="middle" transform="rotate(-90 14 {mt + ph / 2})">'
               f'{html.escape(ylabel)} (log scale)</text>')
    for gi, gname in enumerate(groups):
        gx = ml + gi * group_w + gap / 2
        out.append(f'<text x="{gx + ns * box_w / 2:.1f}" y="{mt + ph + 16}" text-anchor="middle">'
                   f'{html.escape(gname)}</text>')
        for si, (sname, _) in enumerate(series):
            v = np.sort(vals[si][gi]) if gi < len(vals[si]) else np.zeros(0)
            if len(v) == 0:
                continue
            color = _COLORS[si % len(_COLORS)]
            q1, med, q3 = (float(x) for x in np.percentile(v, [25, 50, 75]))
            iqr = q3 - q1
            inside = v[(v >= q1 - 1.5 * iqr) & (v <= q3 + 1.5 * iqr)]
            w_lo, w_hi = float(inside.min()), float(inside.max())
            x0 = gx + si * box_w + 2
            xc = x0 + (box_w - 4) / 2
            tip = f"{gname}, {sname}: n={len(v)}, median {_fmt(med)}, quartiles {_fmt(q1)}-{_fmt(q3)}"
            out.append(f'<g class="box" data-group="{html.escape(gname)}" data-series="{html.escape(sname)}" '
                       f'data-n="{len(v)}" data-median="{med!r}"><title>{html.escape(tip)}</title>')
            out.append(f'<line x1="{xc:.1f}" x2="{xc:.1f}" y1="{py(w_hi):.1f}" y2="{py(w_lo):.1f}" stroke="{color}"/>')
            top, bottom = py(q3), py(q1)
            out.append(f'<rect x="{x0:.1f}" y="{top:.1f}" width="{box_w - 4}" height="{max(bottom - top, 0.5):.1f}" '
                       f'fill="{color}" fill-opacity="0.25" stroke="{color}"/>')
            out.append(f'<line x1="{x0:.1f}" x2="{x0 + box_w - 4:.1f}" y1="{py(med):.1f}" y2="{py(med):.1f}" '
                       f'stroke="{color}" stroke-width="2"/>')
            for o in v[(v < w_lo) | (v > w_hi)]:
                out.append(f'<circle cx="{xc:.1f}" cy="{py(float(o)):.1f}" r="2" fill="none" stroke="{color}"/>')
            out.append("</g>")
    legend_y = mt + 8
    for si, (sname, _) in enumerate(series):
        color = _COLORS[si % len(_COLORS)]
        out.append(f'<rect x="{ml + pw + 10}" y="{legend_y - 5}" width="14" height="10" fill="{color}" '
                   f'fill-opacity="0.25" stroke="{color}"/>')
        out.append(f'<text x="{ml + pw + 30}" y="{legend_y + 4}">{html.escape(sname)}</text>')
        legend_y += 16
    out.append("</svg>")
    return "\n".join(out)
