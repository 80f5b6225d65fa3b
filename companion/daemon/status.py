"""What the operator sees of the running daemon: one ``DaemonStatus`` value.

The status line on the terminal, systemd's STATUS and any other view of the
daemon are formatted from the same value, so they never disagree.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.daemon.pipeline import PipelineStats
from companion.types import Estimate


@dataclass(frozen=True)
class DaemonStatus:
    """The daemon's state over the last second.

    fps: frames processed per second; markers: decoded in the newest frame;
    latency_ms: median capture -> send of the frames sent (None: none sent);
    estimate: the newest estimate given to the link (None: no pose);
    track_state: the filter's state ("acquiring", "tracking", "coasting");
    link_state: the MAVLink link's ("connecting", "handshake", "streaming");
    frames, sent: totals since start; rejected, resets: the filter's counters;
    render_ms: a simulated camera's median render time per frame (None: a real camera).
    """

    fps: float
    markers: int
    latency_ms: float | None
    estimate: Estimate | None
    track_state: str
    link_state: str
    frames: int
    sent: int
    rejected: int
    resets: int
    render_ms: float | None = None

    def line(self) -> str:
        """fps, markers seen, pose, latency, tracking and link state on one line."""
        latency = f"{self.latency_ms:.1f} ms" if self.latency_ms is not None else "-"
        if self.estimate is not None:
            n, e, d = self.estimate.position_ned_m
            pose = f"N {n:+.2f} E {e:+.2f} D {d:+.2f} m yaw {math.degrees(self.estimate.yaw_rad):+.1f} deg"
        else:
            pose = "no pose"
        return (f"{self.fps:5.1f} fps | markers {self.markers} | {pose} | latency {latency} | "
                f"{self.track_state} | link {self.link_state} | "
                f"sent {self.sent} rejected {self.rejected} resets {self.resets}"
                + (f" | render {self.render_ms:.1f} ms" if self.render_ms is not None else ""))


def recent_activity(stats: PipelineStats, window_s: float = 1.0) -> tuple[float, int, float | None, Estimate | None]:
    """(fps, markers in the newest frame, median latency ms, newest estimate) over the newest ``window_s``."""
    recent = stats.recent(window_s)
    fps = (len(recent) - 1) / ((recent[-1].t_ns - recent[0].t_ns) * 1e-9) if len(recent) > 1 else 0.0
    last = recent[-1] if recent else None
    latencies = [r.latency_ns for r in recent if r.latency_ns is not None]
    latency_ms = float(np.median(latencies)) / 1e6 if latencies else None
    return fps, (last.markers if last else 0), latency_ms, (last.estimate if last else None)
