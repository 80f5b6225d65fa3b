"""A simulated camera that follows the simulated vehicle: SITL's true state in, rendered frames out.

The closed loop in a simulator (docs/sitl.md)::

    SITL --SIM_STATE--> link --> SimStateStream --> SimStateHistory
                                                         |  (interpolated to the render time)
    SimulatedCamera thread: render the map as the configured camera sees it from there,
    degrade (noise, blur, exposure), stamp, hand over --> pipeline --> VISION_POSITION_ESTIMATE --> SITL

* **State in.** ``SimStateStream`` is a subscriber of the daemon's one MAVLink
  link (``MavlinkLink.subscribe``): it asks the autopilot for SIM_STATE (108)
  with MAV_CMD_SET_MESSAGE_INTERVAL at ``state_rate_hz`` (again every
  ``request_retry_s`` while it arrives at less than half that rate) and files
  each one in a ``SimStateHistory``. ArduPilot fills SIM_STATE with its
  simulator's truth (``SIM::sim_state_send``): ``q1..q4`` the body -> NED
  attitude (w, x, y, z), ``lat_int``/``lon_int`` in degE7 (its float ``lat``
  and ``lon`` carry degE7 too, not degrees, and are too coarse in a float:
  not used), ``alt`` in metres above mean sea level, ``vn, ve, vd`` in m/s.
  The position goes into the map frame through the map's ``geodetic_origin``
  and ``x_bearing_deg`` (``frames.ned_from_geodetic``: ArduPilot's own
  flat-earth rule), without the 1.1 cm steps of degE7 (``Dequantizer``:
  the velocity is not quantized).
* **Time.** SIM_STATE carries no timestamp: a sample's time comes from when
  the link received it. A busy machine delays the link's thread, by a
  varying amount, and hands it a burst of samples at once, which would stamp
  them all alike: positions up to a burst's length old would be rendered as
  now. The simulator sends them at a regular interval, so ``SendClock``
  stamps them on a regular grid (the interval fitted to the last 200
  arrivals) through the promptest arrival among them, as the attitude's
  clock does with ``time_boot_ms`` (``companion.mavlink.attitude``): the
  error is that arrival's delay. A simulator that falls behind (a stall of
  its process) skips the sends it missed and starts its clock again, as
  ArduPilot does: ``SendClock`` sees three arrivals in a row late on the old
  grid by over an interval, not in one burst, and starts a new one from
  them (on the old grid every later sample would be stamped a stall's
  length early, and the camera, finding no sample near its render time,
  would stall). Late arrivals are held back until the ones after them show
  which they were, so that no frame is rendered from a sample stamped a
  stall's length early; a sample whose send time stays in doubt, and the
  first after a stall (composed before it, its content can be a stall old),
  are dropped.
  SITL must run in real time (speedup 1).
* **Render.** Every ``1 / fps`` the thread renders the state at ``now -
  render_delay`` (interpolated between the two samples around it: positions
  linearly, attitudes by slerp; past the newest sample it extrapolates with
  its velocity for at most ``render_delay``), through the configured
  ``CameraModel`` (intrinsics, distortion, mounting) over the world
  ``companion.sim.simulate.build_world`` makes of the facility map, with the
  configured ``Degradations`` (motion blur from the state's motion over the
  exposure) and, at ``occluders_per_minute``, a person or a box walking
  across the view (``companion.sim.occluders``: each starts beside the view
  the camera has when it is planned, 0.8-1.8 m ahead, and crosses it at
  0.9-1.4 m/s). The frame's ``t_ns`` is the state's time plus
  ``exposure_latency`` and it is handed over no earlier than that, like a
  camera whose driver delivers a frame that long after its exposure.
* **A stopped stream is a stalled camera.** Without a state to render there
  is no frame; ``lost_reason`` says why, as a camera's would, and the
  daemon's health reports it: after ``stall_timeout_s`` from the start that
  it waits for the flight controller (SIM_STATE is asked for when the link
  sees its heartbeat), and that SIM_STATE is missing only ``stall_timeout_s``
  after it was asked for, or after the newest sample.

Nothing downstream knows the frames are rendered.
"""
from __future__ import annotations

import bisect
import collections
import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from companion.capture.source import ThreadedSource
from companion.geometry import frames
from companion.geometry.camera import CameraModel
from companion.geometry.facility_map import FacilityMap, GeodeticOrigin
from companion.mavlink import messages as mm
from companion.mavlink.interval import StreamRequest
from companion.sim import occluders, raster
from companion.sim.degrade import Degradations
from companion.sim.simulate import World, build_world
from companion.types import Frame

log = logging.getLogger(__name__)

SIM_STATE = "SIM_STATE"
HISTORY_LENGTH = 256          # samples kept: seconds of state at any useful rate
RENDER_WINDOW_S = 1.0         # render times reported over this much of the newest time


WAITING_FOR_FC = ("simulated camera: waiting for the flight controller (no heartbeat on the link yet: SITL not "
                  "started, or not on this connection?); SIM_STATE is asked for once it is seen")
WAITING_FOR_STATE = "simulated camera: flight controller seen, SIM_STATE asked for: waiting for the first"


def _seconds_text(ns: int) -> str:
    """A duration as said in a lost reason: never '0.0 s'."""
    return f"{ns * 1e-9:.1f} s" if ns >= 100_000_000 else f"{max(ns, 0) * 1e-6:.0f} ms"


class SimulatedCameraError(ValueError):
    """A simulated camera that cannot work (names what is missing)."""


@dataclass(frozen=True)
class SimState:
    """The simulated vehicle's true state at ``t_ns`` (our monotonic clock).

    position_ned_m: (3,) from the map origin; R_ned_body: (3, 3) body FRD -> NED;
    velocity_ned_m_s: (3,).
    """

    t_ns: int
    position_ned_m: np.ndarray
    R_ned_body: np.ndarray
    velocity_ned_m_s: np.ndarray

    def T_ned_body(self) -> np.ndarray:
        return frames.make_transform(self.R_ned_body, self.position_ned_m)


class SimStateHistory:
    """The newest SIM_STATE samples, interpolated at any time between them (thread-safe)."""

    def __init__(self, length: int = HISTORY_LENGTH):
        self._states: collections.deque[SimState] = collections.deque(maxlen=length)
        self._lock = threading.Lock()

    def add(self, state: SimState) -> bool:
        """File a sample; False (ignored) if it is not newer than the newest."""
        with self._lock:
            if self._states and state.t_ns <= self._states[-1].t_ns:
                return False
            self._states.append(state)
            return True

    def clear(self) -> None:
        with self._lock:
            self._states.clear()

    @property
    def newest_t_ns(self) -> int | None:
        with self._lock:
            return self._states[-1].t_ns if self._states else None

    def at(self, t_ns: int, max_extrapolation_ns: int) -> SimState | None:
        """The state at ``t_ns``: interpolated between the samples around it, extrapolated past
        the newest by its velocity for at most ``max_extrapolation_ns``; None before the oldest
        or further past the newest."""
        with self._lock:
            states = list(self._states)
        if not states or t_ns < states[0].t_ns:
            return None
        newest = states[-1]
        if t_ns >= newest.t_ns:
            ahead_ns = t_ns - newest.t_ns
            if ahead_ns > max_extrapolation_ns:
                return None
            # p(t) = p_newest + v (t - t_newest)
            position = newest.position_ned_m + newest.velocity_ned_m_s * (ahead_ns * 1e-9)
            return SimState(t_ns, position, newest.R_ned_body, newest.velocity_ned_m_s)
        times = [s.t_ns for s in states]
        j = bisect.bisect_right(times, t_ns)
        before, after = states[j - 1], states[j]
        f = (t_ns - before.t_ns) / (after.t_ns - before.t_ns)
        # p = (1 - f) p0 + f p1; R by slerp from R0 to R1
        position = before.position_ned_m + f * (after.position_ned_m - before.position_ned_m)
        velocity = before.velocity_ned_m_s + f * (after.velocity_ned_m_s - before.velocity_ned_m_s)
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([before.R_ned_body, after.R_ned_body])))
        return SimState(t_ns, position, slerp([f]).as_matrix()[0], velocity)


class SendClock:
    """Send times of a message sent at a regular interval, from its receive times (see the module docstring).

    ``arrive(receive_ns, item)`` returns the arrivals whose send times are
    now known, oldest first, as ``(stamp_ns, item)``: at once for an arrival
    on the grid, later for a late one, held until the arrivals after it say
    why it was late. No stamp is later than its arrival.

    The grid: the current run of arrivals (the last ``window`` at most),
    numbered i = 0..n-1, is stamped on the line interval * i + offset under
    them all, through the promptest (offset = min(arrival_i - i * interval)).
    The interval is fitted to the run's prompt arrivals (``_prompt_slope``:
    a delay only ever adds) once it has ``fit_after``; until the first fit,
    an arrival is stamped at its arrival. A fit to a run younger than the
    one the kept interval came from is taken only within 2 % of it: a run
    that began with a long burst can be far off.

    An arrival is late when it comes after its slot on the grid by more
    than half an interval plus the run's usual delay (median minus
    promptest). A late arrival was either delayed on its way (a busy
    receiver's thread woke late: the arrivals after it come on the grid
    again, and it keeps its grid stamp) or is among the first after the
    sender fell behind by more than an interval and started its clock again
    from then (ArduPilot's ``GCS_MAVLINK::update_send``): every later
    arrival is then late on the old grid by about the stall, and stamped on
    it, it would be a stall's length early. ``confirm`` late arrivals in a
    row, each over an interval late and not in one burst (at least half an
    interval apart on average), or ``max_held`` in any way, are that
    restart: a new run starts from them. Of them, those that arrived more
    than half an interval before the slot the later ones put them in may
    have been sent before the stall (or were the prompt first ones after
    it, their followers delayed: the two look alike): no stamp is sure for
    them, and they are dropped. The first of the new run is dropped too:
    composed before the stall and sent after it, its content can be a
    stall old.
    """

    def __init__(self, window: int = 200, fit_after: int = 50, confirm: int = 3, max_held: int = 20):
        self._arrivals_ns: collections.deque[int] = collections.deque(maxlen=window)   # the current run
        self._held: list[tuple[int, object]] = []   # late arrivals, until the ones after them say why
        self.fit_after = fit_after
        self.confirm = confirm
        self.max_held = max_held
        self.restarts = 0
        self.dropped = 0
        self._interval_ns = 0.0
        self._fitted_over = 0   # arrivals the interval was fitted to

    @property
    def holding(self) -> int:
        """Late arrivals not yet stamped."""
        return len(self._held)

    def arrive(self, receive_ns: int, item=None) -> list[tuple[int, object]]:
        """(stamp_ns, item) of every arrival whose send time is now known, oldest first."""
        usual_ns = self._usual_delay_ns()  # of the run, which holding does not change
        if self._late_ns(receive_ns, len(self._held), usual_ns) <= self._interval_ns / 2:
            held, self._held = self._held, []
            return self._settle([*held, (receive_ns, item)])
        self._held.append((receive_ns, item))
        if not self._restarted(usual_ns):
            return []
        held, self._held = self._held, []
        doubtful = self._in_doubt([receive_ns for receive_ns, _ in held])
        self.dropped += doubtful + 1
        self.restarts += 1
        self._arrivals_ns.clear()
        # the new run's first: its arrival times the grid, its content (maybe a stall old) is not returned
        self._settle(held[doubtful:doubtful + 1])
        return self._settle(held[doubtful + 1:])

    def _usual_delay_ns(self) -> float:
        """The run's usual delay on the grid from its oldest arrival (the median lateness); 0 while the
        interval is unknown."""
        if not self._arrivals_ns or self._interval_ns <= 0:
            return 0.0
        return float(np.median(self._lateness_ns()))

    def _late_ns(self, receive_ns: int, held_before: int, usual_ns: float) -> float:
        """How much later than its slot on the grid an arrival at ``receive_ns`` with ``held_before`` held
        ones ahead of it came, beyond the run's usual delay (``_usual_delay_ns``: median minus promptest);
        0 while the interval is unknown."""
        if not self._arrivals_ns or self._interval_ns <= 0:
            return 0.0
        slot = len(self._arrivals_ns) + held_before
        return (receive_ns - self._arrivals_ns[0]) - slot * self._interval_ns - usual_ns

    def _restarted(self, usual_ns: float) -> bool:
        """The held arrivals are a new grid: the last ``confirm`` of them a whole interval late and not in
        one burst, or too many held."""
        held = self._held
        if len(held) >= self.max_held:
            return True
        last = range(len(held) - self.confirm, len(held))
        return (len(held) >= self.confirm
                and min(self._late_ns(held[k][0], k, usual_ns) for k in last) > self._interval_ns
                and held[-1][0] - held[-self.confirm][0] >= (self.confirm - 1) * self._interval_ns / 2)

    def _in_doubt(self, held_ns: list[int]) -> int:
        """How many of the first held arrivals came more than half an interval before the slot the ones
        after them put them in."""
        doubtful = 0
        for j in range(len(held_ns) - 1):
            slot_ns = min(r - (k - j) * self._interval_ns for k, r in enumerate(held_ns) if k > j)
            if held_ns[j] < slot_ns - self._interval_ns / 2:
                doubtful = j + 1
        return doubtful

    def _settle(self, arrivals: list[tuple[int, object]]) -> list[tuple[int, object]]:
        """Onto the current run, each stamped on its grid (at its arrival while the interval is unknown)."""
        settled = []
        for receive_ns, item in arrivals:
            self._arrivals_ns.append(receive_ns)
            if self._update_interval() <= 0:
                settled.append((receive_ns, item))
                continue
            grid_ns = (self._arrivals_ns[0] + self._lateness_ns().min()
                       + (len(self._arrivals_ns) - 1) * self._interval_ns)
            settled.append((min(receive_ns, int(grid_ns)), item))
        return settled

    def _update_interval(self) -> float:
        """The interval (ns; 0 until first fitted): fitted to the run once it has ``fit_after`` arrivals.
        A fit to a younger run than the kept interval's differs from it by 2 % at most (one that began with
        a long burst can be far off), or is not taken."""
        if len(self._arrivals_ns) >= self.fit_after:
            t = np.asarray(self._arrivals_ns, dtype=np.float64) - self._arrivals_ns[0]
            interval_ns = _prompt_slope(t, self._interval_ns)
            if len(t) >= self._fitted_over or abs(interval_ns - self._interval_ns) <= 0.02 * self._interval_ns:
                self._interval_ns, self._fitted_over = interval_ns, max(len(t), self._fitted_over)
        return self._interval_ns

    def _lateness_ns(self) -> np.ndarray:
        """(n,) each arrival of the run: its time after its slot on the grid from the oldest."""
        t = np.asarray(self._arrivals_ns, dtype=np.float64) - self._arrivals_ns[0]
        return t - np.arange(len(t)) * self._interval_ns


def _prompt_slope(t: np.ndarray, guess: float) -> float:
    """(n,) arrival times of slots 0..n-1 (n >= 3): the slope of the line through the promptest arrival of
    the first third and that of the last third (a delay only ever adds), promptest against the line of
    slope ``guess`` (0: least squares' slope), then again against the line found."""
    i = np.arange(len(t), dtype=np.float64)
    slope = guess if guess > 0 else _least_squares_slope(i, t)
    third = len(t) // 3
    for _ in range(2):
        residual = t - slope * i
        a = int(np.argmin(residual[:third]))
        b = len(t) - third + int(np.argmin(residual[-third:]))
        slope = float(t[b] - t[a]) / (b - a)
    return slope


def _least_squares_slope(i: np.ndarray, t: np.ndarray) -> float:
    # slope = cov(i, t) / var(i)
    di = i - i.mean()
    return float(np.dot(di, t - t.mean()) / np.dot(di, di))


class Dequantizer:
    """SIM_STATE positions without the steps of their degE7 latitude and longitude (1.1 cm of latitude).

    A vehicle moving at 1 m/s crosses a step every 11 ms: frames rendered on
    the raw positions jump by up to a centimetre against the truth, more than
    the pose stage's own error. The velocity (vn, ve, vd) is not quantized,
    so each position is taken as the mean, over the last ``window`` samples
    j, of the quantized p_j carried to this sample along the velocity:
    p_i = s_i + mean_j (p_j - s_j), s the velocity's running integral
    (trapezoid rule over the samples' stamps). A gap of more than
    ``max_gap_s`` (a stalled sender, a stopped stream) starts it again.
    """

    def __init__(self, window: int = 50, max_gap_s: float = 0.1):
        self._offsets: collections.deque[np.ndarray] = collections.deque(maxlen=window)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self._integral_m = np.zeros(3)
        self._last: tuple[int, np.ndarray] | None = None

    def smooth(self, t_ns: int, position_m: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
        """(3,) the position of the sample at ``t_ns`` (samples in time order)."""
        if self._last is not None:
            last_ns, last_velocity = self._last
            if not 0 < t_ns - last_ns <= self.max_gap_ns:
                self._offsets.clear()
            # s_i = s_(i-1) + (v_(i-1) + v_i) / 2 (t_i - t_(i-1))
            self._integral_m = self._integral_m + (last_velocity + velocity_m_s) / 2 * ((t_ns - last_ns) * 1e-9)
        self._last = (t_ns, velocity_m_s)
        self._offsets.append(position_m - self._integral_m)
        return self._integral_m + np.mean(self._offsets, axis=0)


class SimStateStream:
    """The link's SIM_STATE subscriber: asks for it, converts it, files it (see the module docstring)."""

    message_types = (SIM_STATE,)

    def __init__(self, history: SimStateHistory, origin: GeodeticOrigin, rate_hz: float = 100.0,
                 request_retry_s: float = 2.0):
        if not (math.isfinite(rate_hz) and 1.0 <= rate_hz <= 400.0):
            raise SimulatedCameraError(f"SIM_STATE rate must be in [1, 400] Hz, got {rate_hz!r}")
        self.history = history
        self.origin = origin
        self.rate_hz = rate_hz
        self.request_retry_s = request_retry_s
        self.received = 0
        self.unusable = 0
        self.request = StreamRequest(mm.mavlink2.MAVLINK_MSG_ID_SIM_STATE, rate_hz, request_retry_s)
        self.first_request_ns: int | None = None   # when SIM_STATE was first asked for (monotonic)
        self.clock = SendClock()
        self.dequantizer = Dequantizer()

    def on_message(self, message, receive_ns: int) -> None:
        # an unusable one still takes its slot on the send grid
        state = sim_state_from_message(message, receive_ns, self.origin)
        if state is None:
            self.unusable += 1
            if self.unusable == 1:
                log.warning("simulated camera: SIM_STATE without lat_int/lon_int or with a non-finite value: "
                            "ignored (ArduPilot SITL from 4.5 on fills lat_int/lon_int)")
        else:
            self.request.arrived(receive_ns)
        for stamp_ns, sample in self.clock.arrive(receive_ns, state):
            if sample is not None:
                self._file(SimState(stamp_ns, sample.position_ned_m, sample.R_ned_body, sample.velocity_ned_m_s))

    def _file(self, state: SimState) -> None:
        """Into the history, its position freed of the degE7 steps (``Dequantizer``)."""
        if self.history.newest_t_ns is not None and state.t_ns <= self.history.newest_t_ns:
            return
        position = self.dequantizer.smooth(state.t_ns, state.position_ned_m, state.velocity_ned_m_s)
        if self.history.add(SimState(state.t_ns, position, state.R_ned_body, state.velocity_ned_m_s)):
            self.received += 1

    @property
    def requests(self) -> int:
        return self.request.requests

    def requests_due(self, now_s: float, target_system: int, target_component: int) -> list:
        """MAV_CMD_SET_MESSAGE_INTERVAL for SIM_STATE while it is missing or slow, every ``request_retry_s``."""
        requests = self.request.due(now_s, target_system, target_component)
        if requests and self.first_request_ns is None:
            self.first_request_ns = time.monotonic_ns()
        return requests


def sim_state_from_message(message, receive_ns: int, origin: GeodeticOrigin) -> SimState | None:
    """A SIM_STATE as a ``SimState`` in NED from ``origin``; None without a usable position or attitude."""
    lat_e7, lon_e7 = int(getattr(message, "lat_int", 0)), int(getattr(message, "lon_int", 0))
    values = [message.q1, message.q2, message.q3, message.q4, message.alt, message.vn, message.ve, message.vd]
    if (lat_e7 == 0 and lon_e7 == 0) or not all(math.isfinite(v) for v in values):
        return None
    try:
        R_ned_body = frames.rotation_from_quaternion([message.q1, message.q2, message.q3, message.q4])
    except ValueError:
        return None
    position = frames.ned_from_geodetic(lat_e7 / frames.DEG_E7, lon_e7 / frames.DEG_E7, float(message.alt),
                                        origin.latitude_deg, origin.longitude_deg, origin.altitude_m)
    return SimState(receive_ns, position, R_ned_body, np.array([message.vn, message.ve, message.vd], dtype=float))


@dataclass(frozen=True)
class SimulatedCameraParams:
    """How the simulated camera renders (config ``source: {kind: simulated_camera}``, docs/sitl.md).

    fps: frames rendered per second; exposure_latency_ms: added to the state's
    time in the frame's stamp (and waited for before handing the frame over);
    render_delay_ms: the state rendered is this far behind now, so that it lies
    between two samples; state_rate_hz: SIM_STATE asked for at this rate;
    stall_timeout_s: no state for this long: the camera is lost (``lost_reason``);
    seed: the sensor noise's and the occluders'; degradations: the
    image-realism knobs; occluders_per_minute: people or boxes crossing the
    view, on average (0: none).
    """

    fps: float = 30.0
    exposure_latency_ms: float = 5.0
    render_delay_ms: float = 20.0
    state_rate_hz: float = 100.0
    stall_timeout_s: float = 1.0
    seed: int = 0
    degradations: Degradations = Degradations()
    occluders_per_minute: float = 0.0


class SimulatedCamera(ThreadedSource):
    """Renders what the simulated vehicle's camera sees, at ``fps`` (see the module docstring).

    ``state_stream`` is the link subscriber that feeds it; ``render_ms()`` the
    median render time of the newest second.
    """

    thread_name = "simulated-camera"

    def __init__(self, facility_map: FacilityMap, camera: CameraModel, params: SimulatedCameraParams,
                 world: World | None = None):
        super().__init__()
        origin = facility_map.frame.geodetic_origin
        if origin is None:
            raise SimulatedCameraError(f"{facility_map.path}: the map has no frame.geodetic_origin: a simulated "
                                       "camera needs it to place the simulator's vehicle in the map")
        self.params = params
        self.camera = camera
        self.world = world if world is not None else build_world(facility_map)
        self.T_map_ned = frames.invert_transform(facility_map.T_ned_map)
        self.history = SimStateHistory()
        self.state_stream = SimStateStream(self.history, origin, params.state_rate_hz)
        self.lost_reason: str | None = None
        self._renderer = raster.Renderer.from_camera(camera)
        self._quad_corners = np.stack([quad.corners_world for quad in self.world.quads])  # (Q, 4, 3)
        self._render_times: collections.deque[tuple[int, int]] = collections.deque(maxlen=512)  # (t_ns, render ns)
        self._render_lock = threading.Lock()
        self._occluder_rng = np.random.default_rng(params.seed + 104729)
        self._occluders: list[occluders.PassingOccluder] = []
        self._next_occluder_s: float | None = None

    def render_ms(self, window_s: float = RENDER_WINDOW_S) -> float | None:
        """Median render time (ms) of the frames rendered in the newest ``window_s``; None if none."""
        with self._render_lock:
            times = list(self._render_times)
        if not times:
            return None
        newest_ns = time.monotonic_ns()
        recent = [render_ns for t_ns, render_ns in times if newest_ns - t_ns <= window_s * 1e9]
        return float(np.median(recent)) / 1e6 if recent else None

    def render_times_ms(self) -> list[float]:
        """Every kept render time (ms), oldest first (benchmarks)."""
        with self._render_lock:
            return [render_ns / 1e6 for _, render_ns in self._render_times]

    # ----------------------------------------------------------- thread

    def _run(self) -> None:
        period_ns = int(1e9 / self.params.fps)
        delay_ns = int(self.params.render_delay_ms * 1e6)
        latency_ns = int(self.params.exposure_latency_ms * 1e6)
        started_ns = time.monotonic_ns()
        last_state_ns: int | None = None   # when a state was last rendered
        next_ns = started_ns
        index = 0
        while not self._stop.is_set():
            if self._stop.wait(max(0.0, (next_ns - time.monotonic_ns()) * 1e-9)):
                return
            now_ns = time.monotonic_ns()
            # a slow render skips ticks rather than queueing them
            next_ns = max(next_ns + period_ns, now_ns - period_ns)
            state = self.history.at(now_ns - delay_ns, max_extrapolation_ns=delay_ns)
            if state is None:
                self._no_state(now_ns, started_ns, last_state_ns)
                continue
            last_state_ns = now_ns
            if self.lost_reason is not None:
                log.info("simulated camera: SIM_STATE came; rendering")
                self.lost_reason = None
            image = self._render(state, index)
            t_ns = state.t_ns + latency_ns
            if self._stop.wait(max(0.0, (t_ns - time.monotonic_ns()) * 1e-9)):
                return
            self._publish(Frame(image=image, t_ns=t_ns, index=index))
            index += 1

    def _no_state(self, now_ns: int, started_ns: int, last_state_ns: int | None) -> None:
        """No state to render: the camera is lost once ``stall_timeout_s`` has passed since it could have had one.

        SIM_STATE is asked for only once the link sees the flight controller (its heartbeat, 1 Hz): until
        then the source waits for the flight controller (said after ``stall_timeout_s`` from its start);
        from the first request on, it is missing only ``stall_timeout_s`` after that request, or after the
        newest sample (or the last frame rendered), whichever is latest. A reason is said once, and again
        only when it changes."""
        timeout_ns = self.params.stall_timeout_s * 1e9
        asked_ns = self.state_stream.first_request_ns
        newest = self.history.newest_t_ns
        if asked_ns is None and newest is None:  # the FC's first heartbeat may take a second to come
            if now_ns - started_ns < timeout_ns + int(mm.FC_HEARTBEAT_PERIOD_S * 1e9):
                return
            reason = WAITING_FOR_FC
        elif now_ns - max(asked_ns or 0, newest or 0, last_state_ns or 0) < timeout_ns:
            if self.lost_reason not in (WAITING_FOR_FC, WAITING_FOR_STATE):
                return
            reason = WAITING_FOR_STATE  # lost while the FC was away: now only waiting for its first SIM_STATE
        elif newest is not None:
            reason = f"simulated camera: no SIM_STATE for {_seconds_text(now_ns - newest)}"
        else:  # asked, and none came
            reason = ("simulated camera: no SIM_STATE from the simulator yet (is it ArduPilot SITL, and does it "
                      f"answer MAV_CMD_SET_MESSAGE_INTERVAL?): asked for {_seconds_text(now_ns - asked_ns)} ago")
        if reason != self.lost_reason:
            self.lost_reason = reason
            log.warning("%s", reason)

    def _render(self, state: SimState, index: int) -> np.ndarray:
        """(H, W) uint8: the degraded image the camera sees from ``state``."""
        started = time.perf_counter_ns()
        T_camera_map = self._T_camera_map(state.T_ned_body())
        quads = self._quads_in_view(T_camera_map) + self._occluder_quads(state.t_ns * 1e-9, T_camera_map)
        rendering = self._renderer.render(quads, T_camera_map, background=40.0, labels=False)
        degradations = self.params.degradations.at(state.t_ns * 1e-9, self.params.seed)
        motion = self._image_motion_px(state, T_camera_map) if degradations.motion_blur else None
        rng = np.random.default_rng([self.params.seed, index])
        image = degradations.apply(rendering.image, rng, motion)
        finished = time.perf_counter_ns()
        with self._render_lock:
            self._render_times.append((time.monotonic_ns(), finished - started))
        return image

    def _quads_in_view(self, T_camera_map: np.ndarray) -> list[raster.TexturedQuad]:
        """The world's quads that may reach the image: not all behind the camera, and not all in front of it
        but beyond one edge of the renderer's canvas. The same image, without preparing the rest one by one."""
        corners = self._quad_corners @ T_camera_map[:3, :3].T + T_camera_map[:3, 3]  # (Q, 4, 3) camera frame
        z = corners[..., 2]
        in_front = z > raster.NEAR_M
        K, (width, height) = self._renderer.canvas_K, self._renderer.canvas_size
        with np.errstate(divide="ignore", invalid="ignore"):
            # u = fx x / z + cx, v = fy y / z + cy
            u = K[0, 0] * corners[..., 0] / z + K[0, 2]
            v = K[1, 1] * corners[..., 1] / z + K[1, 2]
        beyond_an_edge = (u < 0).all(1) | (u > width).all(1) | (v < 0).all(1) | (v > height).all(1)
        seen = in_front.any(axis=1) & ~(in_front.all(axis=1) & beyond_an_edge)
        return [quad for quad, keep in zip(self.world.quads, seen) if keep]

    def _occluder_quads(self, t_s: float, T_camera_map: np.ndarray) -> list[raster.TexturedQuad]:
        """The quads of the people and boxes crossing the view at ``t_s``; plans the next crossing when due."""
        rate_per_s = self.params.occluders_per_minute / 60.0
        if rate_per_s <= 0:
            return []
        rng = self._occluder_rng
        if self._next_occluder_s is None:
            self._next_occluder_s = t_s + rng.exponential(1.0 / rate_per_s)
        if t_s >= self._next_occluder_s:
            self._occluders.append(self._plan_crossing(t_s, frames.invert_transform(T_camera_map), rng))
            self._next_occluder_s = t_s + rng.exponential(1.0 / rate_per_s)
        self._occluders = [o for o in self._occluders if o.t_end_s >= t_s]
        quads = (o.quad_at(t_s) for o in self._occluders)
        return [q for q in quads if q is not None]

    def _plan_crossing(self, t_s: float, T_map_camera: np.ndarray, rng) -> occluders.PassingOccluder:
        """A crossing that starts now beside the current view and walks across it, on the floor."""
        optical_axis = T_map_camera[:3, 2]
        forward = np.array([optical_axis[0], optical_axis[1], 0.0])
        forward /= max(np.linalg.norm(forward), 1e-9)
        right = np.array([forward[1], -forward[0], 0.0])
        distance_m = rng.uniform(0.8, 1.8)
        speed_m_s = rng.uniform(0.9, 1.4)
        direction = 1.0 if rng.uniform() < 0.5 else -1.0
        half_width_m = distance_m * math.tan(math.radians(40.0)) + 0.6
        start = T_map_camera[:3, 3] + distance_m * forward - direction * half_width_m * right
        start[2] = self.world.floor_z_m
        duration_s = 2 * half_width_m / speed_m_s
        kind = "person" if rng.uniform() < 0.6 else "box"
        return occluders.PassingOccluder(kind, t_s, t_s + duration_s, start, direction * speed_m_s * right, -forward,
                                         int(rng.integers(0, 2**31)))

    def _T_camera_map(self, T_ned_body: np.ndarray) -> np.ndarray:
        # T_camera_map = (T_map_ned T_ned_body T_body_camera)^-1
        return frames.invert_transform(self.T_map_ned @ T_ned_body @ self.camera.T_body_camera)

    def _image_motion_px(self, state: SimState, T_camera_map: np.ndarray) -> tuple[float, float]:
        """Image motion (dx, dy) over the exposure of the point 3 m ahead on the optical axis.

        The translation over the exposure is the state's velocity; the rotation is
        not known from one sample and is left out.
        """
        exposure_s = self.params.degradations.exposure_ms * 1e-3
        point_map = frames.transform_points(frames.invert_transform(T_camera_map), [[0.0, 0.0, 3.0]])
        shift_map = self.T_map_ned[:3, :3] @ state.velocity_ned_m_s * exposure_s
        # the camera moves by shift: the scene moves by -shift relative to it
        after, ok = self._renderer.project(point_map - shift_map, T_camera_map)
        before, ok0 = self._renderer.project(point_map, T_camera_map)
        if not (ok[0] and ok0[0]):
            return (0.0, 0.0)
        d = after[0] - before[0]
        return (float(d[0]), float(d[1]))
