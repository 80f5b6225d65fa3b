"""The survey report: ``survey.json`` (per marker numbers) and ``survey.png`` (a top view).

The plot shows the map from above: each marker as a short line along its
face with its symbol, coloured by its position uncertainty, its horizontal
3-sigma uncertainty ellipse (drawn enlarged: millimetres do not show on a hall),
anchors as squares, and the camera path of the frames used, so an operator sees
at a glance which marker needs another look. A weakly linked marker (its symbol
with "?") gets a dashed circle of 3 sd at true size: its sd covers a rival place.
"""
from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from companion.files import write_whole
from companion.survey.survey import SurveyResult

ELLIPSE_SIGMAS = 3.0
SD_COLOURS_M = ((0.005, "tab:green"), (0.02, "tab:orange"), (math.inf, "tab:red"))


def write_report(result: SurveyResult, out_dir) -> tuple[Path, Path]:
    """Write survey.json and survey.png into ``out_dir`` (created); returns their paths. Both or neither: a
    failure or an interruption removes the one already written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path, png_path = out / "survey.json", out / "survey.png"
    write_whole(json_path, json.dumps(report_json(result), indent=2) + "\n")
    try:
        plot(result, png_path)
    except BaseException:
        json_path.unlink(missing_ok=True)
        raise
    return json_path, png_path


def report_json(result: SurveyResult) -> dict:
    """The report as a JSON-ready dict: the frames, the anchors' agreement, and per marker its numbers."""
    def number(value, digits):
        return None if value is None or not math.isfinite(value) else round(float(value), digits)

    markers = [{
        "symbol": s.marker.symbol,
        "anchor": s.anchor,
        "position_m": [number(v, 5) for v in s.marker.T_map_marker[:3, 3]],
        "sd_position_m": number(s.sd_position_m, 5),
        "sd_angle_deg": number(s.sd_angle_deg, 4),
        "frames": s.frames,
        "reprojection_rms_px": number(s.rms_px, 4),
        "weakly_linked": s.weakly_linked,
    } for s in result.markers]
    return {
        "frames_read": result.frames_read,
        "frames_skipped": result.frames_skipped,
        "frames_adjusted": result.frames_adjusted,
        "point_noise_px": number(result.sigma_px, 4),
        "corner_misfit": number(result.corner_misfit, 2),
        "images_fit_one_map": not result.misfit,
        "anchors": [{"symbol": a.symbol, "moved_by_images_m": number(a.position_m, 5),
                     "turned_by_images_deg": number(a.angle_deg, 4), "tied_to_other_anchors": a.tied}
                    for a in result.anchors],
        "not_mapped": [{"symbol": symbol, "frames": frames} for symbol, frames in result.dropped.items()],
        "weakly_linked": [s.marker.symbol for s in result.markers if s.weakly_linked],
        "loose": [s.marker.symbol for s in result.loose],
        "moved": [check.as_json() for check in result.moved],
        "markers": markers,
    }


def plot(result: SurveyResult, path) -> None:
    """survey.png: the top view (see the module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Ellipse

    figure, axes = plt.subplots(figsize=(11, 7), dpi=110)
    path_m = result.camera_path_m
    if len(path_m):
        axes.plot(path_m[:, 0], path_m[:, 1], ".", color="0.6", markersize=2, label="camera (frames used)")
    surveyed = [s for s in result.markers if not s.anchor]
    worst_sd = max((s.sd_position_m for s in surveyed if not s.weakly_linked), default=0.0)
    scale = _enlargement(ELLIPSE_SIGMAS * worst_sd)
    for s in result.markers:
        T = s.marker.T_map_marker
        x, y = T[:2, 3]
        along = T[:2, 0] * s.marker.size_m * 2.0  # the face, drawn twice its width
        colour = "black" if s.anchor else "tab:red" if s.weakly_linked else _colour(s.sd_position_m)
        axes.plot([x - along[0], x + along[0]], [y - along[1], y + along[1]], color=colour, linewidth=2.5)
        label = s.marker.symbol + (" ?" if s.weakly_linked else "")
        axes.annotate(label, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7, color=colour,
                      fontweight="bold" if s.weakly_linked else "normal")
        if s.anchor:
            axes.plot(x, y, "s", color="black", markersize=6, fillstyle="none")
        elif s.weakly_linked:  # its sd covers a rival place: a circle of that radius, not drawn enlarged
            axes.add_patch(Circle((x, y), ELLIPSE_SIGMAS * s.sd_position_m, fill=False, color=colour, linestyle="--",
                                  linewidth=1))
        elif s.covariance is not None:
            width, height, angle_deg = _ellipse(s.covariance[:2, :2], ELLIPSE_SIGMAS * scale)
            axes.add_patch(Ellipse((x, y), width, height, angle=angle_deg, fill=False, color=colour, linewidth=1))
    for limit_m, colour in SD_COLOURS_M:
        label = f"sd < {limit_m * 1000:.0f} mm" if math.isfinite(limit_m) else "sd larger"
        axes.plot([], [], color=colour, linewidth=2.5, label=label)
    axes.plot([], [], "s", color="black", fillstyle="none", label="anchor")
    if any(s.weakly_linked for s in result.markers):
        axes.plot([], [], color="tab:red", linestyle="--", linewidth=1,
                  label=f"? weakly linked: {ELLIPSE_SIGMAS:g} sd, true size")
    axes.set_aspect("equal")
    axes.set_xlabel("map x (m)")
    axes.set_ylabel("map y (m)")
    axes.grid(True, linewidth=0.3)
    axes.set_title(f"{result.facility_map.name}: {len(surveyed)} markers surveyed, "
                   f"{result.frames_adjusted} of {result.frames_read} frames adjusted; "
                   f"ellipses {ELLIPSE_SIGMAS:g} sd, drawn x{scale:g}", fontsize=9)
    axes.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    plt.close(figure)
    write_whole(path, buffer.getvalue())


def _enlargement(radius_m: float, shown_m: float = 0.25) -> float:
    """The largest of 1, 2, 5, 10, 20, 50, ... that draws ``radius_m`` at most ``shown_m``."""
    if radius_m <= 0:
        return 1.0
    steps = [m * 10 ** e for e in range(7) for m in (1, 2, 5)]
    return max([s for s in steps if s * radius_m <= shown_m], default=1.0)


def _colour(sd_position_m: float) -> str:
    return next(colour for limit, colour in SD_COLOURS_M if sd_position_m < limit)


def _ellipse(covariance_xy: np.ndarray, sigmas: float) -> tuple[float, float, float]:
    """(width, height, angle deg) of the ``sigmas`` ellipse of a (2, 2) covariance."""
    values, vectors = np.linalg.eigh(covariance_xy)
    values = np.maximum(values, 0.0)
    angle_deg = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
    return 2 * sigmas * math.sqrt(values[1]), 2 * sigmas * math.sqrt(values[0]), angle_deg
