"""``companion run``: the positioning daemon.

Threads::

    capture/replay --(newest frame)--> pipeline --(publish)--> link ---> flight controller
                                        detect, solve, fuse        heartbeat, handshake, TIMESYNC

* the source's thread (``companion.capture``) captures frames and hands over
  only the newest one;
* ``pipeline`` detects markers, solves the pose, fuses it and sends the
  estimate from the same thread (no queue between fusion and the socket);
* ``link`` and ``heartbeat`` (``companion.mavlink.link``) keep the MAVLink
  connection, the origin handshake and TIMESYNC answers;
* the main thread judges the health on the wall clock
  (``companion.daemon.health``: a stalled camera makes the HEARTBEAT
  CRITICAL and is told by STATUSTEXT), reports the flight controller's
  parameters, prints the one-line status, feeds systemd's watchdog and waits
  for SIGTERM/SIGINT, the end of a replay or a second companion on the link,
  then stops everything in order: pipeline, source (camera released), link
  (socket closed).

The first frame's size is compared with the camera's calibration: another
size of the same aspect ratio scales the intrinsics (logged), another aspect
ratio stops the daemon with an error.

With no ``--config`` it runs the embedded default: the bundled recorded
sequence and ``maps/warehouse.yaml``, MAVLink to ``udpout:127.0.0.1:14550``.
"""
from __future__ import annotations

import collections
import logging
import os
import select
import sys
import threading
import time
from pathlib import Path

import numpy as np

from companion.geometry import frames
from companion.daemon.config import Config, ConfigError, ReplayConfig, SimulatedCameraConfig
from companion.daemon.health import STALL_MAX_S, Health, HealthState
from companion.detect.detector import Detector, DetectorParams
from companion.fusion import PoseFilter
from companion.geometry.attitude import AttitudeHistory, AttitudeLookup
from companion.geometry.camera import CameraError, CameraModel
from companion.geometry.facility_map import load_map
from companion.mavlink import fc_params
from companion.mavlink.attitude import AttitudeStream
from companion.mavlink.link import LinkState, MavlinkLink
from companion.mavlink.messages import FC_HEARTBEAT_PERIOD_S, SEVERITY_CRITICAL, SEVERITY_WARNING
from companion.daemon.notify import Notifier
from companion.daemon.map_watch import MapWatch
from companion.daemon.mount_watch import MOUNT_WATCH_SDS, MountWatch, MountWatchParams
from companion.daemon.pipeline import Pipeline
from companion.daemon.record import GROUNDTRUTH_FILE, Recorder
from companion.daemon.web import LiveView
from companion.daemon.status import DaemonStatus, fit_to_terminal, recent_activity
from companion.geometry.pose import PoseSolver
from companion.capture.replay import SEQUENCE_FILE, replay_source, sequence_camera, sequence_map_path
from companion.capture.simulated import SimulatedCamera
from companion.capture.source import FrameSource
from companion.capture.v4l2 import opencv_warnings, v4l2_source
from companion.params import ParamsError
from companion.types import Frame
from companion.yaml_input import Where

log = logging.getLogger("companion")

# The pipeline loop must have turned this recently for the watchdog to be fed.
PIPELINE_STALL_S = 5.0
SYSLOG_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3, logging.CRITICAL: 2}
LOG_LEVELS = ("debug", "info", "warning", "error")
# The FC's VISO_DELAY_MS is judged against the measured latency: wait this long for SENT_FOR_LATENCY frames.
PARAMETER_LATENCY_WAIT_S = 10.0
SENT_FOR_LATENCY = 30


def detector_params_for(config: Config) -> DetectorParams:
    """The config's detector section (stages as nested mappings, ``DetectorParams.from_mapping``),
    with the marker layout (parity, dictionary) taken from the map; errors name the file and the key."""
    facility_map = config.facility_map
    layout = {"parity": facility_map.parity, "dictionary": facility_map.dictionary}
    where = Where(str(config.path), ConfigError, "detector")
    for key, value in layout.items():
        if key in config.detector and config.detector[key] != value:
            raise where.error(f"{config.detector[key]!r} differs from the map's {value!r} ({facility_map.path})", key)
    try:
        return DetectorParams.from_mapping({**config.detector, **layout})
    except ParamsError as error:
        raise where.error(error.reason, error.key) from None


def make_detector(config: Config, camera: CameraModel | None = None) -> Detector:
    """The daemon's detector: the config's parameters, the map's layout, the camera's lens for the corners."""
    return Detector(detector_params_for(config), camera=camera or config.camera)


def _takes_a_line_now(stream) -> bool:
    """Whether ``stream`` takes a status line without waiting for its reader (a pipe or terminal that nobody
    reads fills up; one with room for a line, PIPE_BUF at least, takes it whole). A stream with no file
    descriptor never waits."""
    try:
        return bool(select.select([], [stream.fileno()], [], 0)[1])
    except (OSError, ValueError, AttributeError):  # io.StringIO (UnsupportedOperation), a closed stream
        return True


class Daemon:
    """Builds the stages from a Config and runs the threads until stopped."""

    def __init__(self, config: Config, status_stream=None, record_frames: int = 2000):
        self.config = config
        self.status_stream = status_stream
        # the status line is made (for the stream and systemd's STATUS=) only for a daemon given a stream;
        # the stream may be given up later (_write_status), the line for systemd goes on
        self._makes_status_line = status_stream is not None
        self._status_held_up = False   # its reader was not reading at the last line
        detector = make_detector(config)
        self.source = make_source(config)
        self.attitude_stream, attitude, self._attitude_text = attitude_source(config, self.source)
        self.link = MavlinkLink(config.mavlink, attitude=self.attitude_stream)
        if isinstance(self.source, SimulatedCamera):
            # the simulator's vehicle state arrives over the same connection
            self.link.subscribe(self.source.state_stream)
        self.pipeline = Pipeline(
            detector,
            PoseSolver(config.facility_map, config.camera, config.pose),
            PoseFilter(config.fusion),
            self.link,
            T_map_ned=frames.invert_transform(config.facility_map.T_ned_map),
            attitude=attitude,
        )
        self.pipeline.stats.records = collections.deque(maxlen=record_frames)
        self.health = Health(self._say, attitude_expected=attitude is not None,
                             first_frame_within_s=first_frame_within_s(config))
        self.pipeline.observers.append(self.health.observe)
        # a marker the pose stage keeps leaving out is said once (docs/survey.md), and weighed from then on as
        # uncertain as it was seen to be off (the pipeline's solver: the one for the frames' size)
        self.pipeline.observers.append(MapWatch(
            config.facility_map, self.link, on_disagreement=lambda *offset: self.pipeline.solver.loosen(*offset),
            on_map_error=lambda *sd: self.pipeline.solver.loosen_all(*sd)))
        # so is a camera mount (or FC level) that puts the markers' down away from the FC's
        self.pipeline.observers.append(MountWatch(self.link, MountWatchParams(
            min_angle_deg=MOUNT_WATCH_SDS * config.pose.attitude_sd_deg)))
        self.link.on_parameters = self._on_fc_parameters
        self.notifier = Notifier()
        self.stop_event = threading.Event()
        self.failed = False
        # the config or its input cannot work (a calibration of another aspect, a replay with no readable
        # frame): exit status 2, which systemd does not restart (RestartPreventExitStatus=2)
        self.bad_input = False
        self._frame_shape: tuple[int, int] | None = None   # (height, width) of the first frame, the one in use
        self._resized_frames = 0
        self._sizes_said: set[tuple[int, int]] = set()
        self._fc_parameters: tuple[int, dict, float] | None = None  # (autopilot, values, when they came)
        self._judged_parameters: tuple[int, dict] | None = None     # the last (autopilot, values) judged
        self._pipeline_alive_s = time.monotonic()
        self._pipeline_thread = threading.Thread(target=self._run_pipeline, name="pipeline", daemon=True)
        self.recorder, self.live_view = self._make_observers()

    def _make_observers(self) -> tuple[Recorder | None, LiveView | None]:
        """The flight recording and the live view (``record``, ``status.http``), as pipeline observers."""
        config = self.config
        recorder = live_view = None
        if config.http is not None:   # first: a busy port must fail before a recording folder is made
            stats = self.pipeline.stats
            live_view = LiveView(config.http, config.facility_map, self.status, lambda: list(stats.records),
                                 lambda: list(self.link.statustext_history))
            self.pipeline.observers.append(live_view)
        if config.record is not None:
            replayed = config.source.path if isinstance(config.source, ReplayConfig) else None
            groundtruth = replayed / GROUNDTRUTH_FILE if replayed is not None and replayed.is_dir() else None
            recorder = Recorder(config.record, config.camera, Path(config.facility_map.path), groundtruth,
                                source=describe_source(config),
                                attitude_of_frames=self.attitude_stream is None and self.pipeline.attitude is not None)
            # first: the frame an observer logs something about is the newest the recording has (events.csv)
            self.pipeline.observers.insert(0, recorder)
            if self.attitude_stream is not None:   # the FC's samples as they arrive (link thread)
                self.attitude_stream.on_sample = recorder.attitude
        return recorder, live_view

    def _compare_with_recording(self) -> None:
        """A replayed recording names the camera that took it and the map its markers hung on (sequence.yaml;
        ``companion run --record`` keeps a copy of the map). The config's, which are the ones used, differing
        from them pose the frames wrong (rejected poses, 'markers lost' with markers in view, a mount warning):
        said once at the start, with what differs."""
        source = self.config.source
        if not isinstance(source, ReplayConfig) or not source.path.is_dir():
            return
        named = source.path / SEQUENCE_FILE
        differences = self._camera_differences(source.path)
        if differences:
            log.warning("the config's camera (%s) is not the one %s names, which took the replayed frames: %s; "
                        "the config's is used, and poses are only right if it is the camera that took them",
                        self.config.path, named, "; ".join(differences))
        recorded_map, differences = self._map_differences(source.path)
        if differences:
            log.warning("the config's map (%s) is not the one %s names (%s): %s; the config's is used, and poses "
                        "are only right where it is the map of the recorded site", self.config.facility_map.path,
                        named, recorded_map, "; ".join(differences))

    def _camera_differences(self, folder: Path) -> list[str]:
        """What the config's camera has otherwise than the recording's ([] when it names none, or a broken one:
        not ours to judge)."""
        try:
            recorded = sequence_camera(folder)
        except ValueError:
            return []
        if recorded is None:
            return []
        ours = self.config.camera
        if (ours.width, ours.height) != (recorded.width, recorded.height):
            try:  # the pipeline scales a camera to frames of another size and the same aspect
                ours = ours.scaled_to(recorded.width, recorded.height)
            except CameraError:
                pass
        return ours.differences(recorded)

    def _map_differences(self, folder: Path) -> tuple[Path | None, list[str]]:
        """(the recording's map, what the config's map has otherwise); [] as for the camera."""
        try:
            recorded = sequence_map_path(folder)
            return recorded, self.config.facility_map.differences(load_map(recorded)) if recorded else []
        except ValueError:
            return None, []

    def run(self) -> int:
        """Run until ``stop_event`` is set (signal, end of replay); returns the exit code."""
        self.link.start()
        for observer in (self.recorder, self.live_view):
            if observer is not None:
                observer.start()
        self.source.start()
        clock_offset_ns = getattr(self.source, "clock_offset_ns", None)
        if clock_offset_ns is not None:
            log.info("replay %s: recorded t_ns 0 is monotonic %d ns", self.config.source.path, clock_offset_ns)
        self._pipeline_thread.start()
        self.notifier.ready(status="running")
        log.info("running: source %s, map %s, MAVLink %s", describe_source(self.config),
                 self.config.facility_map.path, self.config.mavlink.connection)
        log.info("attitude: %s", self._attitude_text)
        self._compare_with_recording()
        try:
            self._supervise()
        finally:
            self.shutdown()
        # Non-zero after a failure, so that systemd's Restart=on-failure restarts us (not for bad input: 2).
        return 2 if self.bad_input else 1 if self.failed else 0

    def shutdown(self) -> None:
        self.stop_event.set()
        self.notifier.stopping()
        if self._pipeline_thread.is_alive():
            self._pipeline_thread.join(timeout=5.0)
        self.pipeline.detector.close()
        self.source.close()
        for observer in (self.recorder, self.live_view):
            if observer is not None:
                observer.close()
        self.link.close("companion: failed, no more vision" if self.failed else "companion: stopped, no more vision")
        self.notifier.close()
        self._print_summary()

    def _run_pipeline(self) -> None:
        try:
            while not self.stop_event.is_set():
                self._pipeline_alive_s = time.monotonic()
                frame = self.source.get(timeout_s=0.2)
                if frame is None:
                    if self.source.finished:
                        log.info("source finished")
                        self.failed |= self.source.error is not None
                        if self._frame_shape is None and self.source.error is None:
                            log.error("%s: not one readable frame (%d unreadable); stopping",
                                      describe_source(self.config), self.source.counters.corrupt)
                            self.bad_input = True
                        break
                    continue
                if self._frame_shape is None and not self._adopt_frame_size(frame):
                    self.failed = self.bad_input = True
                    break
                if frame.image.shape[:2] != self._frame_shape:
                    self._skip_resized(frame)
                    continue
                self.pipeline.process(frame)
        except Exception:
            log.exception("pipeline failed")
            self.failed = True
        finally:
            self.stop_event.set()

    def _adopt_frame_size(self, frame: Frame) -> bool:
        """The first frame against the calibration: the same size, or scaled intrinsics (the same
        aspect ratio: said in the log); False (logged) when the calibration cannot describe it."""
        self._frame_shape = frame.image.shape[:2]
        height, width = frame.image.shape[:2]
        camera = self.config.camera
        if (width, height) == (camera.width, camera.height):
            return True
        try:
            scaled = camera.scaled_to(width, height)
        except CameraError as error:
            log.error("%s: camera: %s; stopping", self.config.path, error)
            return False
        log.warning("camera calibrated for %dx%d, frames are %dx%d: intrinsics scaled by %.4g (same aspect ratio)",
                    camera.width, camera.height, width, height, width / camera.width)
        self.pipeline.detector = make_detector(self.config, scaled)
        self.pipeline.solver = PoseSolver(self.config.facility_map, scaled, self.config.pose)
        return True

    def _skip_resized(self, frame: Frame) -> None:
        """A frame of another size than the first (a camera that changed its mode, a mixed image folder): the
        intrinsics describe the first size only, so it is skipped and counted; said once per new size."""
        self._resized_frames += 1
        height, width = frame.image.shape[:2]
        if (width, height) not in self._sizes_said:
            self._sizes_said.add((width, height))
            first_height, first_width = self._frame_shape
            self._say(f"camera frames {width}x{height}, not {first_width}x{first_height}: skipped",
                      SEVERITY_WARNING, "camera")

    def _say(self, text: str, severity: int, topic: str | None = None) -> None:
        """A health message: to the log and, as STATUSTEXT, to the flight controller (topic: see Health)."""
        level = (logging.ERROR if severity <= SEVERITY_CRITICAL else
                 logging.WARNING if severity <= SEVERITY_WARNING else logging.INFO)
        log.log(level, "%s", text)
        self.link.statustext(f"companion: {text}", severity, topic)

    def _on_fc_parameters(self, autopilot: int, values: dict) -> None:
        """The link read the FC's parameters (link thread): judged by the main thread, see _report_fc_parameters."""
        self._fc_parameters = (autopilot, values, time.monotonic())

    def _report_fc_parameters(self, now_s: float) -> None:
        """Judge the FC's parameters once the latency is measured (or after a while): log each one that
        stops or degrades vision fusion, and tell them in a few STATUSTEXTs (fc_params.statustexts). The
        same values read again (the link reads them at every reconnection) are not told again."""
        pending = self._fc_parameters
        if pending is None:
            return
        autopilot, values, arrived_s = pending
        if (autopilot, values) == self._judged_parameters:
            self._fc_parameters = None
            log.debug("flight controller parameters read again, unchanged: not judged again")
            return
        latencies = [r.latency_ns for r in list(self.pipeline.stats.records) if r.latency_ns is not None]
        if len(latencies) < SENT_FOR_LATENCY and now_s - arrived_s < PARAMETER_LATENCY_WAIT_S:
            return
        self._fc_parameters = None
        self._judged_parameters = (autopilot, values)
        latency_ms = float(np.median(latencies)) / 1e6 if len(latencies) >= SENT_FOR_LATENCY else None
        mavlink = self.config.mavlink
        expected = fc_params.Expected(lever_arm_m=tuple(float(v) for v in self.config.camera.T_body_camera[:3, 3]),
                                      sends_velocity=mavlink.send_vision_speed or mavlink.send_odometry,
                                      latency_ms=latency_ms)
        checks = fc_params.check_parameters(autopilot, values, expected)
        if not checks:
            log.info("flight controller: autopilot %d is neither ArduPilot nor PX4: its parameters are not checked",
                     autopilot)
            return
        problems = fc_params.problems(checks)
        for check in problems:
            blocks = check.verdict == fc_params.BLOCKS
            log.log(logging.ERROR if blocks else logging.WARNING,
                    "flight controller parameter %s = %s %s vision fusion: %s (expected %s; companion check-fc)",
                    check.name, check.value_text(), check.verdict, check.why, check.expected)
        for text, severity in fc_params.statustexts(checks):
            self.link.statustext(text, severity)
        if not problems:
            log.info("flight controller parameters fit what we send: %s",
                     ", ".join(f"{c.name}={c.value_text()}" for c in checks))

    def _supervise(self) -> None:
        interval_s = self.config.status_interval_s
        watchdog_s = self.notifier.watchdog_interval_s
        tty = self.status_stream is not None and self.status_stream.isatty()
        next_status = next_watchdog = time.monotonic()
        next_log = next_status + max(interval_s, 5.0)
        while not self.stop_event.wait(0.05):
            now = time.monotonic()
            if not self.link.alive:
                log.error("link threads ended unexpectedly; stopping")
                self.failed = True
                break
            if self.link.state is LinkState.DUPLICATE:
                log.error("refusing to run: %s", self.link.duplicate)
                self.failed = True
                break
            self.link.set_critical(self.health.check(lost_reason=self.source.lost_reason).critical)
            self._report_fc_parameters(now)
            # Feed the watchdog only while the pipeline loop turns (with or without frames).
            if watchdog_s and now >= next_watchdog and now - self._pipeline_alive_s < PIPELINE_STALL_S:
                self.notifier.watchdog()
                next_watchdog = now + watchdog_s
            if self._makes_status_line and now >= next_status:
                line = self.status_line()
                if tty:
                    self._write_status("\r\x1b[K" + fit_to_terminal(line, self._terminal_columns()))
                elif now >= next_log:
                    self._write_status(line + "\n")
                    next_log = now + max(interval_s, 5.0)
                self.notifier.status(line)
                next_status = now + interval_s
        if self.status_stream is not None:  # the last line whole: nothing rewrites it
            self._write_status(("\r\x1b[K" if tty else "") + self.status_line() + "\n")

    def _terminal_columns(self) -> int:
        """The status terminal's width now (it may have been resized); 80 when it cannot be asked."""
        try:
            return os.get_terminal_size(self.status_stream.fileno()).columns
        except (OSError, ValueError, AttributeError):
            return 80

    def _write_status(self, text: str) -> None:
        """The status line to ``status_stream``. A stream that fails (its reader gone: ``companion run | head``,
        a closed terminal) is said once in the log and given up: the vehicle's positioning goes on without it."""
        if self.status_stream is None:
            return
        if not _takes_a_line_now(self.status_stream):
            # waiting for the reader would hold up the supervisor: health reports, the watchdog, SIGTERM
            if not self._status_held_up:
                log.warning("status line: its reader is not reading (a full pipe: `companion run | less` not "
                            "scrolled?); lines are left out until it reads, the daemon goes on")
                self._status_held_up = True
            return
        if self._status_held_up:
            log.info("status line: its reader reads again")
            self._status_held_up = False
        try:
            self.status_stream.write(text)
            self.status_stream.flush()
        except (OSError, ValueError) as error:  # ValueError: a stream already closed
            log.warning("status line: cannot write it any more (%s); the daemon goes on, status in the log and "
                        "systemd's status only", error)
            self.status_stream = None

    def status(self) -> DaemonStatus:
        """The daemon's state over the last second of wall-clock time (see ``companion.daemon.status``);
        any thread may ask."""
        now_ns = time.monotonic_ns()
        fps, markers, latency_ms, estimate = recent_activity(self.pipeline.stats, now_ns)
        health: HealthState = self.health.assess(now_ns, self.source.lost_reason)
        counters = self.pipeline.pose_filter.counters
        return DaemonStatus(fps=fps, markers=markers, latency_ms=latency_ms, estimate=estimate,
                            state=health.state, state_s=health.since_s, reasons=health.reasons,
                            critical=health.critical, track_state=self.pipeline.pose_filter.state.value,
                            link_state=self.link.state.value, frames=self.pipeline.stats.frames,
                            sent=self.pipeline.stats.sent, rejected=counters.rejected, resets=counters.resets,
                            attitude=health.attitude, link_down=self.link.down_reason,
                            fc_unheard_s=self.link.fc_unheard_s, fc_unheard_why=self.link.fc_unheard_why,
                            render_ms=self.source.render_ms() if isinstance(self.source, SimulatedCamera) else None)

    def status_line(self) -> str:
        return self.status().line()

    def _print_summary(self) -> None:
        stats, source = self.pipeline.stats, self.source.counters
        log.info("frames %d, sent %d, dropped %d, corrupt %d, repeated %d, resized %d, camera reopens %d, link %s",
                 stats.frames, stats.sent, source.dropped, source.corrupt, source.repeated, self._resized_frames,
                 source.reopens, dict(self.link.counters.sent))
        for name, median_ms, p99_ms in stats.stage_table():
            log.info("stage %-14s median %7.2f ms  p99 %7.2f ms", name, median_ms, p99_ms)


def first_frame_within_s(config: Config) -> float:
    """How long the first frame may take before health calls it a stall: a simulated camera asks for the
    simulator's state only once it has heard the flight controller (its heartbeat: up to a second), then waits
    its own ``stall_timeout_s`` (and says why, as its lost reason, if nothing comes)."""
    if isinstance(config.source, SimulatedCameraConfig):
        return FC_HEARTBEAT_PERIOD_S + config.source.params.stall_timeout_s
    return STALL_MAX_S


def attitude_source(config: Config, source: FrameSource
                    ) -> tuple[AttitudeStream | None, AttitudeLookup | None, str]:
    """(the link's attitude stream, the pipeline's attitude lookup, what it is for the log) the config asks for.

    A camera: the flight controller's ATTITUDE over MAVLink. A replay: its
    recording's attitude.csv (a live autopilot's attitude has nothing to do
    with recorded frames), or none; unless ``attitude.source: link`` asks
    for the link's whatever the source.
    """
    settings = config.attitude
    if settings.source == "none":
        return None, None, "off (attitude.source: none): poses without the flight controller's roll and pitch"
    if isinstance(config.source, ReplayConfig) and settings.source == "auto":
        lookup = source.attitude_lookup(settings.max_age_s)
        if lookup is None:
            return None, None, "the replay has no attitude.csv: poses without the flight controller's roll and pitch"
        return None, lookup, "from the replay's attitude.csv"
    history = AttitudeHistory(settings.max_age_s)
    return (AttitudeStream(history, settings.rate_hz), history.lookup,
            f"ATTITUDE from the flight controller at {settings.rate_hz:g} Hz, stale after {settings.max_age_s:g} s")


def make_source(config: Config) -> FrameSource:
    source = config.source
    if isinstance(source, ReplayConfig):
        return replay_source(source.path, realtime=source.realtime, loop=source.loop, fps=source.fps,
                             fps_option=source.fps_option)
    if isinstance(source, SimulatedCameraConfig):
        return SimulatedCamera(config.facility_map, config.camera, source.params)
    return v4l2_source(source.device, source.width, source.height, source.fps, source.pixel_format,
                       source.stall_timeout_s)


def describe_source(config: Config) -> str:
    source = config.source
    if isinstance(source, ReplayConfig):
        pace = "real time" if source.realtime else "as fast as possible"
        return f"replay of {source.path} ({pace}{', looping' if source.loop else ''})"
    if isinstance(source, SimulatedCameraConfig):
        return (f"simulated camera at {source.params.fps:g} fps following the simulator's SIM_STATE "
                f"on {config.mavlink.connection}")
    return f"V4L2 camera {source.device}"


# ------------------------------------------------------------------- CLI

class _JournalFormatter(logging.Formatter):
    """``<priority>name: message``: journald reads the level from the prefix."""

    def format(self, record: logging.LogRecord) -> str:
        return f"<{SYSLOG_PRIORITY.get(record.levelno, 6)}>{record.name}: {record.getMessage()}"


def setup_logging(level: str = "info") -> None:
    """Log to stderr at ``level`` (one of LOG_LEVELS); under systemd with journald priorities."""
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("JOURNAL_STREAM"):
        handler.setFormatter(_JournalFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(getattr(logging, level.upper()))
    opencv_warnings(shown=level == "debug")
