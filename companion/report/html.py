"""``companion report DIR``: one self-contained HTML page about a recorded flight.

Sections (each plot a PNG embedded in the page, made with matplotlib):
summary, track over the map, position and yaw against time, vision
availability with every gap and its reason, the daemon's log while it
recorded (events.csv), capture -> send latency, markers (detections and corrections
per marker), and the error against ``groundtruth.csv`` when the folder has one.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")   # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from companion.files import write_whole  # noqa: E402
from companion.geometry.facility_map import FacilityMap  # noqa: E402
from companion.plan import MapPlane, markers_plan  # noqa: E402
from companion.report.flight_log import FlightLog  # noqa: E402

REPORT_FILE = "report.html"
# verdict -> colour of its band in the availability timeline
VERDICT_COLOURS = {"ok": "#2e9d4a", "no marker": "#9aa3ad", "pose withheld": "#e08a1e",
                   "filter gating": "#c0392b", "link": "#6c5ce7"}
STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; max-width: 1100px; margin: 24px auto; color: #1d2228; padding: 0 16px; }
h1 { font-size: 22px; } h2 { font-size: 17px; margin-top: 32px; border-bottom: 1px solid #d8dde3; padding-bottom: 4px; }
table { border-collapse: collapse; margin: 8px 0; } td, th { padding: 3px 10px; border-bottom: 1px solid #e4e7eb;
text-align: left; font-variant-numeric: tabular-nums; } th { background: #f3f5f7; }
img { max-width: 100%; } .note { color: #5b6570; }
tr.warning td { background: #fff4d6; } tr.error td { background: #fde2e1; }
"""


def write_report(log: FlightLog, facility_map: FacilityMap | None, out: Path | None = None) -> Path:
    """Write the report (default ``<folder>/report.html``); returns its path."""
    out = out or log.folder / REPORT_FILE
    sections = [
        ("Summary", summary_table(log, facility_map)),
        ("Track over the map", _image(track_figure(log, facility_map)) + _track_note(log, facility_map)),
        ("Position and yaw against time", _image(time_figure(log))),
        ("Vision availability", _image(availability_figure(log)) + gaps_table(log)),
        ("Log while recording", events_table(log)),
        ("Capture → send latency", _image(latency_figure(log)) + stage_table(log)),
        ("Markers", (_image(markers_figure(log)) if log.markers else "") + markers_table(log)),
    ]
    if log.truth_ned_m is not None:
        sections.append(("Error against the ground truth", _image(error_figure(log)) + error_table(log)))
    title = f"Flight report: {log.folder.name}"
    body = "\n".join(f"<section><h2>{html.escape(name)}</h2>\n{content}</section>" for name, content in sections)
    write_whole(out, f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}"
                f"</title><style>{STYLE}</style></head>\n<body><h1>{html.escape(title)}</h1>\n{body}\n"
                "</body></html>\n")
    return out


# ------------------------------------------------------------------- tables

def _rows(rows, header=None, classes=None) -> str:
    """A table; ``classes``: a CSS class per row ('' for none)."""
    head = "<tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr>" if header else ""
    classes = classes or [""] * len(rows)
    body = "".join((f"<tr class={kind}>" if kind else "<tr>") + "".join(f"<td>{html.escape(str(c))}</td>" for c in row)
                   + "</tr>" for row, kind in zip(rows, classes))
    return f"<table>{head}{body}</table>"


def _ms(values: np.ndarray, percentile: float = 50) -> str:
    values = values[np.isfinite(values)]
    return f"{np.percentile(values, percentile):.1f} ms" if len(values) else "–"


def summary_table(log: FlightLog, facility_map: FacilityMap | None) -> str:
    info = log.info
    fixes = int(log.fix.sum())
    gaps = log.gaps()
    rows = [
        ("folder", str(log.folder)),
        ("source", info.get("source", "–")),
        ("started (UTC)", info.get("started_utc", "–")),
        ("map", facility_map.path if facility_map is not None else "none (plots in NED)"),
        ("duration", f"{log.duration_s:.1f} s"),
        ("pipeline frames", f"{len(log.frame)} ({1 / log.frame_period_s:.1f} fps)" if log.frame_period_s
         else str(len(log.frame))),
        ("recorded frames", f"{info.get('frames', '–')} (dropped {info.get('dropped_frames', 0)}), "
                            f"{info.get('video_codec', '–')}, stopped: {info.get('stopped', '–')}"),
        ("fresh vision fixes", f"{fixes} of {len(log.frame)} frames ({100 * fixes / len(log.frame):.0f} %)"),
        ("estimates sent", str(int(log.sent.sum()))),
        ("capture → send", f"median {_ms(log.latency_ms)}, p99 {_ms(log.latency_ms, 99)}"),
        ("log lines", _events_summary(log)),
        ("gaps in vision", f"{len(gaps)}, longest {max((g.duration_s for g in gaps), default=0):.2f} s"
                           f" ({max(gaps, key=lambda g: g.duration_s).reason})" if gaps else "none"),
    ]
    if log.truth_ned_m is not None:
        errors = log.errors_m()
        errors = errors[np.isfinite(errors)]
        if len(errors):
            rows.append(("position error (estimate)", f"median {np.median(errors):.3f} m, "
                                                      f"p95 {np.percentile(errors, 95):.3f} m"))
    return _rows(rows)


def gaps_table(log: FlightLog) -> str:
    gaps = log.gaps()
    if not gaps:
        return "<p class=note>No gap: a fresh fix at least every 0.2 s (or 3 frames).</p>"
    rows = [(f"{g.start_s:.2f}", f"{g.end_s:.2f}", f"{g.duration_s:.2f}", g.frames, g.reason,
             ", ".join(f"{k} {v}" for k, v in g.reasons.items())) for g in gaps]
    return _rows(rows, ("from s", "to s", "length s", "frames", "reason", "frames by verdict"))


def _events_summary(log: FlightLog) -> str:
    if log.events is None:
        return "not recorded (no events.csv)"
    warnings = sum(event.is_warning for event in log.events)
    return f"{len(log.events)} ({warnings} warning{'' if warnings == 1 else 's'} or error{'' if warnings == 1 else 's'})"


def events_table(log: FlightLog) -> str:
    if log.events is None:
        return "<p class=note>This recording has no events.csv (recorded by a version before it was kept).</p>"
    if not log.events:
        return "<p class=note>Nothing logged while recording.</p>"
    rows = [("before the first frame" if e.t_s is None else f"{e.t_s:.2f}", "" if e.frame is None else e.frame,
             e.level, e.text) for e in log.events]
    return ("<p class=note>Every line the daemon logged while it recorded (INFO and above; what the flight "
            "controller was told as STATUSTEXT is among them), at the newest frame when it was logged.</p>"
            + _rows(rows, ("s", "frame", "level", "text"), [_level_class(e.level) for e in log.events]))


def _level_class(level: str) -> str:
    """The row's colour in the log table: warnings in amber, errors in red, the rest plain."""
    return {"WARNING": "warning", "ERROR": "error", "CRITICAL": "error"}.get(level, "")


def stage_table(log: FlightLog) -> str:
    names = ("detect", "pose", "fuse", "send")
    rows = [(name, _ms(log.stage_ms[:, i]), _ms(log.stage_ms[:, i], 99)) for i, name in enumerate(names)]
    rows.append(("total", _ms(log.stage_ms.sum(axis=1)), _ms(log.stage_ms.sum(axis=1), 99)))
    return _rows(rows, ("stage", "median", "p99"))


def markers_table(log: FlightLog) -> str:
    if not log.markers:
        return "<p class=note>No detections.csv, or no marker decoded.</p>"
    rows = [(m.symbol, m.id, m.frames, m.square, m.circles, m.corrected_frames, m.corrections) for m in log.markers]
    return _rows(rows, ("marker", "id", "frames", "by its square", "by its circles", "frames corrected",
                        "symbols corrected"))


def error_table(log: FlightLog) -> str:
    rows = []
    for which, label in (("estimated", "fused estimate"), ("measured", "raw pose (per frame)")):
        errors = log.errors_m(which)
        yaw = np.abs(log.yaw_errors_deg(which))
        ok = np.isfinite(errors)
        if ok.any():
            rows.append((label, int(ok.sum()), f"{np.median(errors[ok]):.3f}", f"{np.percentile(errors[ok], 95):.3f}",
                         f"{np.max(errors[ok]):.3f}", f"{np.median(yaw[np.isfinite(yaw)]):.2f}"))
    return _rows(rows, ("", "frames", "median m", "p95 m", "max m", "median |yaw| deg"))


# ------------------------------------------------------------------- figures

def _image(figure) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(figure)
    encoded = base64.b64encode(buffer.getvalue()).decode()
    return f'<img alt="plot" src="data:image/png;base64,{encoded}">'


def _track_note(log: FlightLog, facility_map: FacilityMap | None) -> str:
    frame = "the map frame (x, y; z up)" if facility_map is not None else "local NED (east right, north up)"
    return (f"<p class=note>Seen from above in {frame}: the fused estimate (line), the raw per-frame poses "
            "(dots), the ground truth when known (dashed); markers as short bars with the side they face.</p>")


def _plan_xy(log: FlightLog, ned: np.ndarray, plane: MapPlane | None) -> np.ndarray:
    """(N, 2) top-view coordinates: map x, y with a map, else east, north."""
    if plane is None:
        return ned[:, [1, 0]]
    xy = np.full((len(ned), 2), np.nan)
    ok = np.all(np.isfinite(ned[:, :3]), axis=1)
    if ok.any():
        xy[ok] = plane.positions_m(ned[ok, :3])[:, :2]
    return xy


def track_figure(log: FlightLog, facility_map: FacilityMap | None):
    figure, axes = plt.subplots(figsize=(10, 6.5))
    plane = MapPlane(facility_map) if facility_map is not None else None
    if facility_map is not None:
        for m in markers_plan(facility_map):
            (cx, cy), (hx, hy), (nx, ny) = m.centre_m, m.half_width_m, m.normal
            axes.plot([cx - hx, cx + hx], [cy - hy, cy + hy], color="black", lw=2.5)
            axes.plot([cx, cx + 0.25 * nx], [cy, cy + 0.25 * ny], color="black", lw=0.8)
            axes.annotate(m.symbol, (cx + 0.5 * nx, cy + 0.5 * ny), fontsize=7, ha="center", va="center",
                          color="#444")
    measured = _plan_xy(log, log.measured, plane)
    estimated = _plan_xy(log, log.estimated, plane)
    axes.plot(measured[:, 0], measured[:, 1], ".", ms=3, color="#e08a1e", label="raw pose")
    axes.plot(estimated[:, 0], estimated[:, 1], "-", lw=1.5, color="#1f6fd1", label="fused estimate")
    if log.truth_ned_m is not None:
        truth = _plan_xy(log, log.truth_ned_m, plane)
        axes.plot(truth[:, 0], truth[:, 1], "--", lw=1, color="black", label="ground truth")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("map x (m)" if plane else "east (m)")
    axes.set_ylabel("map y (m)" if plane else "north (m)")
    axes.grid(alpha=0.3)
    axes.legend(loc="best", fontsize=8)
    return figure


def time_figure(log: FlightLog):
    figure, rows = plt.subplots(4, 1, figsize=(10, 8), sharex=True)
    labels = ("north (m)", "east (m)", "down (m)", "yaw (deg)")
    for row, (axes, label) in enumerate(zip(rows, labels)):
        column = row if row < 3 else 5
        scale = 1.0 if row < 3 else 180 / math.pi
        axes.plot(log.t_s, log.measured[:, column] * scale, ".", ms=2.5, color="#e08a1e", label="raw pose")
        axes.plot(log.t_s, log.estimated[:, column] * scale, "-", lw=1.2, color="#1f6fd1", label="fused estimate")
        if row < 3:
            sd = log.position_sd_m[:, row]
            axes.fill_between(log.t_s, log.estimated[:, row] - 2 * sd, log.estimated[:, row] + 2 * sd,
                              color="#1f6fd1", alpha=0.15, lw=0, label="±2σ")
        if log.truth_ned_m is not None:
            truth = log.truth_ned_m[:, row] if row < 3 else log.truth_yaw_rad * scale
            axes.plot(log.t_s, truth, "--", lw=0.9, color="black", label="ground truth")
        axes.set_ylabel(label)
        axes.grid(alpha=0.3)
    rows[0].legend(loc="upper right", fontsize=8, ncol=4)
    rows[-1].set_xlabel("time (s)")
    return figure


def availability_figure(log: FlightLog):
    figure, axes = plt.subplots(figsize=(10, 2.6))
    period = log.frame_period_s or 0.033
    names = list(VERDICT_COLOURS)
    for lane, verdict in enumerate(names):
        spans = [(t - period / 2, period) for t in log.t_s[log.verdict == verdict]]
        axes.broken_barh(spans, (lane - 0.4, 0.8), facecolors=VERDICT_COLOURS[verdict], lw=0)
    for gap in log.gaps():
        axes.axvspan(gap.start_s, gap.end_s, color="#c0392b", alpha=0.08, lw=0)
    warned = [e.t_s for e in log.events or () if e.is_warning and e.t_s is not None]
    for t_s in warned:
        axes.axvline(t_s, color="#c0392b", lw=0.8, ls="--")
    axes.set_yticks(range(len(names)), ["fix sent" if n == "ok" else n for n in names])
    axes.invert_yaxis()
    axes.set_xlabel("time (s)")
    axes.set_xlim(log.t_s[0] - period, log.t_s[-1] + period)
    axes.grid(axis="x", alpha=0.3)
    axes.set_title("each frame's verdict (shaded: the gaps listed below"
                   + ("; dashed: a warning in the daemon's log)" if warned else ")"), fontsize=9)
    return figure


def latency_figure(log: FlightLog):
    figure, axes = plt.subplots(figsize=(10, 3))
    latency = log.latency_ms[np.isfinite(log.latency_ms)]
    if len(latency):
        axes.hist(latency, bins=min(60, max(10, len(latency) // 5)), color="#1f6fd1")
        for value, name in ((np.median(latency), "median"), (np.percentile(latency, 99), "p99")):
            axes.axvline(value, color="black", ls="--", lw=1)
            axes.annotate(f"{name} {value:.1f} ms", (value, axes.get_ylim()[1] * 0.9), fontsize=8, xytext=(3, 0),
                          textcoords="offset points")
    else:
        axes.text(0.5, 0.5, "nothing was sent", ha="center", va="center", transform=axes.transAxes)
    axes.set_xlabel("capture → send (ms)")
    axes.set_ylabel("frames")
    return figure


def markers_figure(log: FlightLog):
    markers = log.markers[:40]
    figure, axes = plt.subplots(figsize=(10, 3.2))
    x = np.arange(len(markers))
    axes.bar(x, [m.square for m in markers], color="#1f6fd1", label="by its square")
    axes.bar(x, [m.circles for m in markers], bottom=[m.square for m in markers], color="#e08a1e",
             label="by its corner circles")
    axes.plot(x, [m.corrected_frames for m in markers], "kD", ms=4, label="frames with RS corrections")
    axes.set_xticks(x, [m.symbol for m in markers], rotation=60, fontsize=8)
    axes.set_ylabel("frames decoded")
    axes.legend(fontsize=8)
    return figure


def error_figure(log: FlightLog):
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(10, 5), sharex=True)
    top.plot(log.t_s, log.errors_m("measured"), ".", ms=2.5, color="#e08a1e", label="raw pose")
    top.plot(log.t_s, log.errors_m("estimated"), "-", lw=1.2, color="#1f6fd1", label="fused estimate")
    top.set_ylabel("position error (m)")
    top.legend(fontsize=8)
    top.grid(alpha=0.3)
    bottom.plot(log.t_s, log.yaw_errors_deg("measured"), ".", ms=2.5, color="#e08a1e")
    bottom.plot(log.t_s, log.yaw_errors_deg("estimated"), "-", lw=1.2, color="#1f6fd1")
    bottom.set_ylabel("yaw error (deg)")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    return figure
