"""The annotated camera image of the live view: what the pipeline made of one frame.

Each decoded marker is outlined (green: used by the pose; red: mapped but not
in an accepted pose, left out as inconsistent or the pose withheld; grey: not
in the map) with its symbol, the detector path that
found it ("sq" its black square, "ci" its corner circles) and the number of
Reed-Solomon corrections; a banner at the top says the frame number, the
pose stage's verdict and the estimate.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from companion.daemon.pipeline import FrameRecord
from companion.daemon.record import verdict

# BGR
USED = (80, 220, 80)
REJECTED = (60, 60, 240)
UNMAPPED = (170, 170, 170)
CIRCLE = (255, 200, 0)
BANNER_OK = (40, 120, 40)
BANNER_NO_FIX = (30, 60, 170)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def annotate(image: np.ndarray, record: FrameRecord) -> np.ndarray:
    """(H, W, 3) uint8 BGR: the (H, W) gray frame with its markers and verdict drawn on it."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = max(image.shape[1] / 640.0, 0.5)
    thickness = max(1, round(2 * scale))
    solution = record.solution
    used = set(solution.marker_ids) if solution is not None and solution.measurement is not None else set()
    unmapped = set(solution.unmapped_ids) if solution is not None else set()
    for detection in record.detections:
        if detection.id in unmapped:
            color = UNMAPPED
        elif detection.id in used:
            color = USED
        else:
            color = REJECTED
        corners = np.round(np.asarray(detection.corners_px) * 16).astype(np.int32)  # 4 fractional bits
        cv2.polylines(canvas, [corners.reshape(-1, 1, 2)], True, color, thickness, cv2.LINE_AA, shift=4)
        for x, y in np.asarray(detection.circles_px).reshape(-1, 2):
            cv2.circle(canvas, (int(round(x * 16)), int(round(y * 16))), int(4 * scale * 16), CIRCLE, thickness,
                       cv2.LINE_AA, shift=4)
        label = f"{detection.symbol} {'sq' if detection.path == 'square' else 'ci'}"
        if detection.corrected:
            label += f" +{detection.corrected}"
        x, y = np.asarray(detection.corners_px)[0]
        _text(canvas, label, (int(x), int(y) - int(6 * scale)), 0.5 * scale, color, thickness)
    _banner(canvas, record, scale, thickness)
    return canvas


def _banner(canvas: np.ndarray, record: FrameRecord, scale: float, thickness: int) -> None:
    why = verdict(record)
    if why == "pose withheld" and record.solution is not None:
        why = f"pose withheld: {record.solution.status}"
    text = f"#{record.index}  {why}"
    estimate = record.estimate
    if estimate is not None:
        n, e, d = estimate.position_ned_m
        text += f"  N {n:+.2f} E {e:+.2f} D {d:+.2f} yaw {math.degrees(estimate.yaw_rad):+.0f}"
        if not estimate.tracking:
            text += " (coasting)"
    height = int(22 * scale)
    cv2.rectangle(canvas, (0, 0), (canvas.shape[1], height), BANNER_OK if verdict(record) == "ok" else BANNER_NO_FIX,
                  cv2.FILLED)
    cv2.putText(canvas, text, (int(6 * scale), int(16 * scale)), FONT, 0.5 * scale, (255, 255, 255),
                max(1, thickness // 2), cv2.LINE_AA)


def _text(canvas: np.ndarray, text: str, origin: tuple[int, int], size: float, color, thickness: int) -> None:
    """Text with a dark outline, readable on any background."""
    cv2.putText(canvas, text, origin, FONT, size, (0, 0, 0), thickness + 2, cv2.LINE_AA)
    cv2.putText(canvas, text, origin, FONT, size, color, thickness, cv2.LINE_AA)
