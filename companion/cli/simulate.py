"""``companion simulate OUT --map M ...``: render a synthetic sequence (``companion.sim.simulate``)."""
from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading

import numpy as np

from companion.cli.output import output_dir, removed_if_left_empty
from companion.geometry.camera import CameraModel, load_camera
from companion.geometry.facility_map import FacilityMap, load_map
from companion.sim import trajectory as trajectories
from companion.sim.degrade import DegradationError, Degradations
from companion.sim.raster import MAX_SUPERSAMPLE, RenderError, check_render_size
from companion.sim.simulate import (DEFAULT_CAMERA, DEFAULT_DEGRADATIONS, VIDEO_CODECS, AttitudeNoise, SimulationError,
                                    Simulator, build_world, frame_times_ns, write_sequence)

# The ranges of the options' numbers (docs/simulator.md, "Inputs"); the realism knobs' are Degradations'.
MAX_METRES = 100_000.0  # coordinates and lengths: more is a typo (millimetres for metres)
MAX_HEADING_DEG = 360.0
SPEED_RANGE_M_S = (0.01, 50.0)
ACCEL_RANGE_M_S2 = (0.01, 50.0)
MAX_PASSES = 1000
MAX_OCCLUDERS = 100
REALISM_OPTIONS = {"--exposure-ms": "exposure_ms", "--blur": "optics_blur_sigma_px", "--read-noise": "read_noise_dn",
                   "--shot-noise": "shot_noise_gain", "--jpeg": "jpeg_quality", "--vignette": "vignette_strength",
                   "--exposure-wander": "exposure_wander"}
ATTITUDE_OPTIONS = {"--attitude-rate": "rate_hz", "--attitude-noise": "noise_deg", "--attitude-bias": "bias_deg"}


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", help="output sequence folder (created)")
    parser.add_argument("--map", required=True, help="facility map YAML (maps/*.yaml)")
    parser.add_argument("--camera", help="camera file: a config with a 'camera' section, a bare camera "
                                         "section, or an OpenCV calibration YAML (default: 640x480, "
                                         "70 deg HFOV, forward, tilted 20 deg down)")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    parser.add_argument("--seed", type=int, default=0, help="seed for every random choice (default 0)")
    parser.add_argument("--video", action="store_true", help="write video.avi instead of PNG frames")
    parser.add_argument("--codec", choices=sorted(VIDEO_CODECS), default="mp4v",
                        help="video codec: mp4v (small, lossy; default) or ffv1 (lossless, large)")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar on stderr (default: on for more than 60 frames)")
    parser.add_argument("--supersample", type=int, default=1,
                        help=f"anti-aliasing factor 1..{MAX_SUPERSAMPLE} (default 1; costs its square in time "
                             "and memory)")

    t = parser.add_argument_group("trajectory (a CSV or a pattern)")
    t.add_argument("--trajectory", help="CSV of t_ns,x_m,y_m,z_m,qw,qx,qy,qz (T_map_body); "
                                        "a groundtruth.csv works")
    t.add_argument("--pattern", choices=("hover", "path", "waypoints", "lawnmower", "figure8"), default="hover")
    t.add_argument("--duration", type=float, default=5.0, help="seconds (hover, figure8)")
    t.add_argument("--center", type=_floats(3), default=None, help="x,y,z map metres (hover, figure8)")
    t.add_argument("--heading", type=float, default=0.0,
                   help="body heading, deg ccw from map +x, -360..360 (hover, lawnmower, figure8)")
    t.add_argument("--start", type=_floats(3), help="x,y,z (lawnmower)")
    t.add_argument("--end", type=_floats(3), help="x,y,z (lawnmower)")
    t.add_argument("--sweep", type=float, default=1.0, help="side step over all passes, m (lawnmower)")
    t.add_argument("--passes", type=int, default=2, help="number of passes, 1..1000 (lawnmower)")
    t.add_argument("--speed", type=float, default=1.0, help="m/s, 0.01..50 (lawnmower, waypoints, path)")
    t.add_argument("--max-accel", type=float, default=1.0, help="m/s^2, 0.01..50 (lawnmower, waypoints, path)")
    t.add_argument("--waypoints", type=_waypoints,
                   help="'x,y,z,heading;x,y,z,heading;...' (waypoints: stop at each; path: fly through)")
    t.add_argument("--size", type=_floats(2), default=(1.5, 0.8), help="along,across half-extents, m (figure8)")
    t.add_argument("--period", type=float, default=8.0, help="seconds per eight (figure8)")
    t.add_argument("--drift", type=float, default=0.04, help="hover wander, m (hover)")

    r = parser.add_argument_group("realism (the image knobs of companion.sim.degrade.Degradations)")
    d = DEFAULT_DEGRADATIONS
    r.add_argument("--exposure-ms", type=float, default=d.exposure_ms,
                   help="exposure time for motion blur (default %(default)s)")
    r.add_argument("--motion-blur", action=argparse.BooleanOptionalAction, default=d.motion_blur,
                   help=f"smear by the image motion during the exposure (default {'on' if d.motion_blur else 'off'})")
    r.add_argument("--blur", type=float, default=d.optics_blur_sigma_px,
                   help="optics blur sigma, px (default %(default)s)")
    r.add_argument("--read-noise", type=float, default=d.read_noise_dn,
                   help="read noise sigma, DN (default %(default)s)")
    r.add_argument("--shot-noise", type=float, default=d.shot_noise_gain,
                   help="shot noise gain, DN per DN (default %(default)s)")
    r.add_argument("--jpeg", type=int, default=d.jpeg_quality, help="JPEG quality round trip (default 0: off)")
    r.add_argument("--vignette", type=float, default=d.vignette_strength,
                   help="corner darkening 0..1 (default %(default)s)")
    r.add_argument("--exposure-wander", type=float, default=d.exposure_wander,
                   help="slow exposure changes, log amplitude (default 0: off; 0.3 is noticeable)")
    r.add_argument("--occluders", type=int, default=0, help="people/boxes crossing the view, 0..100 (default 0)")

    a = parser.add_argument_group("attitude.csv (the flight controller's roll and pitch: the truth, noise, bias)")
    noise = AttitudeNoise()
    a.add_argument("--attitude", action=argparse.BooleanOptionalAction, default=True,
                   help="write attitude.csv (default on)")
    a.add_argument("--attitude-noise", type=float, default=noise.noise_deg,
                   help="noise sd on each roll and pitch sample, deg (default %(default)s)")
    a.add_argument("--attitude-bias", type=float, default=noise.bias_deg,
                   help="bias added to every roll and pitch, deg (default %(default)s)")
    a.add_argument("--attitude-rate", type=float, default=noise.rate_hz,
                   help="samples per second (default %(default)s)")


def _floats(n: int):
    def parse(text: str):
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}") from None
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}")
        return values
    return parse


def _waypoints(text: str):
    rows = [_floats(4)(part) for part in text.split(";") if part.strip()]
    if len(rows) < 2:
        raise argparse.ArgumentTypeError("need at least two waypoints 'x,y,z,heading;x,y,z,heading'")
    return rows


def check_options(args) -> None:
    """Every number the options give, each named by its option when it is not a finite number in its range
    (docs/simulator.md, "Inputs"), before anything is read or rendered."""
    def require(ok: bool, option: str, rule: str, value) -> None:
        if not ok:
            raise SimulationError(f"{option} must be {rule}, not {_shown(value)}")

    def within(option: str, value: float, low: float, high: float, unit: str) -> None:
        require(math.isfinite(value) and low <= value <= high, option, f"{low:g}..{high:g} {unit}", value)

    def positive(value: float) -> bool:
        return math.isfinite(value) and value > 0

    if not positive(args.fps):
        raise SimulationError(f"--fps must be positive, got {args.fps}")
    require(args.seed >= 0, "--seed", "0 or more", args.seed)
    require(1 <= args.supersample <= MAX_SUPERSAMPLE, "--supersample", f"1..{MAX_SUPERSAMPLE}", args.supersample)
    require(positive(args.duration), "--duration", "a positive number of seconds", args.duration)
    for option in ("--center", "--start", "--end"):
        point = getattr(args, option[2:])
        require(point is None or _in_reach(point), option, f"x,y,z within +-{MAX_METRES:g} m", point)
    for number, waypoint in enumerate(args.waypoints or (), start=1):
        require(_in_reach(waypoint[:3]) and _heading(waypoint[3]), "--waypoints",
                f"x,y,z within +-{MAX_METRES:g} m and a heading within +-{MAX_HEADING_DEG:g} degrees, each",
                f"{_shown(waypoint)} (waypoint {number})")
    within("--heading", args.heading, -MAX_HEADING_DEG, MAX_HEADING_DEG, "degrees")
    within("--sweep", args.sweep, -MAX_METRES, MAX_METRES, "m")
    require(1 <= args.passes <= MAX_PASSES, "--passes", f"1..{MAX_PASSES}", args.passes)
    within("--speed", args.speed, *SPEED_RANGE_M_S, "m/s")
    within("--max-accel", args.max_accel, *ACCEL_RANGE_M_S2, "m/s^2")
    require(all(math.isfinite(v) and 0 <= v <= MAX_METRES for v in args.size), "--size",
            f"two numbers 0..{MAX_METRES:g} m", args.size)
    require(positive(args.period), "--period", "a positive number of seconds", args.period)
    within("--drift", args.drift, 0, MAX_METRES, "m")
    require(0 <= args.occluders <= MAX_OCCLUDERS, "--occluders", f"0..{MAX_OCCLUDERS}", args.occluders)


def _in_reach(point) -> bool:
    return all(math.isfinite(v) and abs(v) <= MAX_METRES for v in point)


def _heading(value: float) -> bool:
    return math.isfinite(value) and abs(value) <= MAX_HEADING_DEG


def _shown(value) -> str:
    """A number as given; a point as its comma-separated numbers."""
    return ",".join(f"{v:g}" for v in value) if isinstance(value, (tuple, list)) else str(value)


def degradations_from_args(args) -> Degradations:
    """``DEFAULT_DEGRADATIONS`` with the realism options; a knob out of its range named by its option."""
    knobs = _checked_options(args, REALISM_OPTIONS, Degradations, DegradationError, "degradations: ")
    return DEFAULT_DEGRADATIONS.with_(motion_blur=args.motion_blur, **knobs)


def attitude_from_args(args) -> AttitudeNoise | None:
    """attitude.csv's noise (None: --no-attitude); a setting out of its range named by its option."""
    settings = _checked_options(args, ATTITUDE_OPTIONS, AttitudeNoise, SimulationError)
    return AttitudeNoise(**settings) if args.attitude else None


def _checked_options(args, options: dict[str, str], make, error_type, prefix: str = "") -> dict:
    """{field: value} of ``options`` (--option -> field of ``make``), each value checked alone by ``make``: a
    SimulationError naming the option of one out of its range."""
    values = {field: getattr(args, option[2:].replace("-", "_")) for option, field in options.items()}
    for option, field in options.items():
        try:
            make(**{field: values[field]})
        except error_type as error:
            raise SimulationError(f"{option}: {str(error).removeprefix(prefix)}") from None
    return values


def camera_from_args(args) -> CameraModel:
    """The --camera file's camera (or the default one), known to fit the renderer at --supersample."""
    camera = load_camera(args.camera) if args.camera else CameraModel.from_config(DEFAULT_CAMERA,
                                                                                  "<default camera>")
    with named_camera(args):
        check_render_size(camera.width, camera.height, args.supersample)
    return camera


@contextlib.contextmanager
def named_camera(args):
    """A RenderError (the frame too large to draw) as a SimulationError naming the camera and --supersample."""
    try:
        yield
    except RenderError as error:
        camera = f"--camera {args.camera}" if args.camera else "the default camera"
        raise SimulationError(f"{camera} at --supersample {args.supersample}: {error}") from None


def trajectory_from_args(args, facility_map: FacilityMap) -> trajectories.Trajectory:
    if args.trajectory:
        return trajectories.read_trajectory_csv(args.trajectory)
    centre = args.center
    if centre is None:
        positions = np.array([m.T_map_marker[:3, 3] for m in facility_map.markers.values()])
        centre = (*positions[:, :2].mean(axis=0), 1.5)
    if args.pattern == "hover":
        return trajectories.hover(centre, args.heading, args.duration, args.drift, args.seed)
    if args.pattern == "figure8":
        return trajectories.figure_eight(centre, args.size, args.period, args.heading, args.duration)
    if args.pattern == "lawnmower":
        if args.start is None or args.end is None:
            raise SimulationError("--pattern lawnmower needs --start x,y,z and --end x,y,z")
        with named_options("--start, --end"):  # the numbers are checked: only where they are can be wrong
            return trajectories.lawnmower(args.start, args.end, args.sweep, args.passes, args.heading, args.speed,
                                          args.max_accel)
    if args.waypoints is None:
        raise SimulationError(f"--pattern {args.pattern} needs --waypoints 'x,y,z,heading;...'")
    with named_options("--waypoints"):  # likewise: a path that does not move
        if args.pattern == "path":
            return trajectories.smooth_path(args.waypoints, args.speed, args.max_accel)
        return trajectories.waypoints(args.waypoints, args.speed, 0.0, args.max_accel)


@contextlib.contextmanager
def named_options(options: str):
    """A TrajectoryError about the flight as a SimulationError naming the options it comes from."""
    try:
        yield
    except trajectories.TrajectoryError as error:
        raise SimulationError(f"{options}: {error}") from None


@contextlib.contextmanager
def sigterm_interrupts():
    """SIGTERM (`timeout`, a cancelled job, `kill`) stops the render as Ctrl-C does: the unfinished sequence
    is removed (by default the process would die and leave it beside OUT)."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():  # only the main thread takes signals
        yield
        return
    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(args) -> int:
    try:
        check_options(args)
        degradations = degradations_from_args(args)
        attitude = attitude_from_args(args)
        facility_map = load_map(args.map)
        camera = camera_from_args(args)
        traj = trajectory_from_args(args, facility_map)
        world = build_world(facility_map, args.seed)
        with named_camera(args):  # a distorting lens draws on a larger canvas than its frame
            simulator = Simulator(world, camera, traj, degradations, args.seed, args.supersample, args.occluders)
        options = {k: v for k, v in vars(args).items() if k not in ("command", "out") and not callable(v)}
        frame_count = len(frame_times_ns(traj.duration_s, args.fps))
        with removed_if_left_empty(args.out), sigterm_interrupts():
            output_dir(args.out, "OUT")
            out = write_sequence(args.out, simulator, args.fps, args.map, args.video, args.progress,
                                 {"options": options}, args.codec, attitude)
    except ValueError as error:
        print(f"companion simulate: {error}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({frame_count} frames)")
    return 0
