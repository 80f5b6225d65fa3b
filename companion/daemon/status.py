"""What the operator sees of the running daemon: one ``DaemonStatus`` value.

The status line on the terminal, systemd's STATUS and any other view of the
daemon are formatted from the same value, so they never disagree. It is a
plain dataclass of plain values (and the newest Estimate), measured on the
wall clock: a camera that stalls shows 0 fps at once, not the rate of its
last good second.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.daemon.pipeline import PipelineStats
from companion.types import Estimate


@dataclass(frozen=True)
class DaemonStatus:
    """The daemon's state over the last second of wall-clock time.

    fps: frames processed in the last second; markers: decoded in the newest
    frame of that second (0 if none came); latency_ms: median capture -> send
    of the frames sent in it (None: none sent); estimate: the newest estimate
    given to the link in it (None: no pose);
    state: the health (``companion.daemon.health``: "camera lost", "camera
    stalled", "starting", "no markers", "no pose", or the filter's
    "acquiring", "tracking", "coasting"); state_s: how long a problem state
    has lasted; reasons: what it rests on ("reprojection 42", ...);
    critical: the HEARTBEAT says CRITICAL (camera stalled or lost);
    track_state: the filter's state; link_state: the MAVLink link's
    ("connecting", "handshake", "streaming", "duplicate"); link_down: why its
    transport is down ("cannot open: ...", "lost: ..."; None while it is open);
    frames, sent: totals since start; rejected, resets: the filter's counters;
    attitude: the flight controller's attitude in the pose stage ("ok",
    "stale", "waiting"; "off" when none is expected, and then not shown);
    render_ms: a simulated camera's median render time per frame (None: a
    real camera, and then not shown); fc_unheard_s: how long no flight
    controller has been heard on the open link (``MavlinkLink.fc_unheard_s``;
    None: one is heard, or the link is down), shown beside the link's state
    (``link streaming, no FC heard 12 s``) for as long as it lasts, with
    ``fc_unheard_why`` (``MavlinkLink.fc_unheard_why``) when there is a clue.
    """

    fps: float
    markers: int
    latency_ms: float | None
    estimate: Estimate | None
    state: str
    state_s: float
    reasons: tuple[str, ...]
    critical: bool
    track_state: str
    link_state: str
    frames: int
    sent: int
    rejected: int
    resets: int
    attitude: str = "off"
    render_ms: float | None = None
    link_down: str | None = None
    fc_unheard_s: float | None = None
    fc_unheard_why: str | None = None

    def state_text(self) -> str:
        """``camera stalled 3.2 s: no frame for 3.2 s``; the bare state when all is well."""
        text = self.state
        if self.state_s and self.state not in ("acquiring", "tracking", "coasting"):
            text += f" {self.state_s:.1f} s"
        return text + (": " + ", ".join(self.reasons) if self.reasons else "")

    def line(self) -> str:
        """fps, markers seen, pose, latency, health, attitude and link state on one line."""
        latency = f"{self.latency_ms:.1f} ms" if self.latency_ms is not None else "-"
        if self.estimate is not None:
            n, e, d = self.estimate.position_ned_m
            pose = f"N {n:+.2f} E {e:+.2f} D {d:+.2f} m yaw {math.degrees(self.estimate.yaw_rad):+.1f} deg"
        else:
            pose = "no pose"
        attitude = "" if self.attitude == "off" else f"attitude {self.attitude} | "
        link = self.link_state + (f" ({self.link_down})" if self.link_down and self.link_state == "connecting" else "")
        if self.fc_unheard_s is not None and self.link_state != "connecting":
            link += f", no FC heard {self.fc_unheard_s:.0f} s"
            link += f" ({self.fc_unheard_why})" if self.fc_unheard_why else ""
        return (f"{self.fps:5.1f} fps | markers {self.markers} | {pose} | latency {latency} | "
                f"{self.state_text()} | {attitude}link {link} | "
                f"sent {self.sent} rejected {self.rejected} resets {self.resets}"
                + (f" | render {self.render_ms:.1f} ms" if self.render_ms is not None else ""))


def recent_activity(stats: PipelineStats, now_ns: int, window_s: float = 1.0
                    ) -> tuple[float, int, float | None, Estimate | None]:
    """(fps, markers in the newest frame, median latency ms, newest estimate) over the ``window_s``
    of wall-clock (monotonic) time before ``now_ns``."""
    recent = stats.recent(window_s, now_ns)
    fps = len(recent) / window_s
    last = recent[-1] if recent else None
    latencies = [r.latency_ns for r in recent if r.latency_ns is not None]
    latency_ms = float(np.median(latencies)) / 1e6 if latencies else None
    return fps, (last.markers if last else 0), latency_ms, (last.estimate if last else None)


def fit_to_terminal(line: str, columns: int) -> str:
    """``line`` cut to a terminal ``columns`` wide (its last column left free). A carriage return goes back
    to the start of the last row only: a line that wrapped (190 characters on an 80-column ssh session)
    would leave its first rows behind at every update. The whole line still goes to the log every few
    seconds without a terminal, to systemd's STATUS= and to the live view."""
    return line[:max(columns - 1, 1)]
