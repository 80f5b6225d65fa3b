"""The flight controller's parameters that decide whether it fuses our vision, and their judgement.

The link reads them (``PARAM_REQUEST_READ``) when a flight controller
appears; ``check_parameters`` judges each value against what the daemon
sends (the body origin with the camera's lever arm applied, its messages,
its measured capture -> send latency): ``ok``, ``degrades`` (vision is used,
but worse or partly) or ``blocks`` (vision is not used at all). Used by the
daemon (log + STATUSTEXT) and by ``companion check-fc`` (a table).
The daemon logs every problem with its reason; ``statustexts`` says them to
the flight controller in as few STATUSTEXTs as carry them (50 characters
each), blocking ones first: a FC that answers nothing gets two, not ten.
docs/daemon.md ("Flight controller set-up") gives the reasons.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from companion.mavlink.messages import SEVERITY_CRITICAL, SEVERITY_WARNING, STATUSTEXT_MAX_CHARS, mavlink2

OK, DEGRADES, BLOCKS = "ok", "degrades", "blocks"
ARDUPILOT = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = mavlink2.MAV_AUTOPILOT_PX4
AUTOPILOT_NAMES = {ARDUPILOT: "ArduPilot", PX4: "PX4"}

ARDUPILOT_PARAMETERS = ("AHRS_EKF_TYPE", "VISO_TYPE", "EK3_SRC1_POSXY", "EK3_SRC1_POSZ", "EK3_SRC1_YAW",
                        "EK3_SRC1_VELXY", "VISO_DELAY_MS", "VISO_POS_X", "VISO_POS_Y", "VISO_POS_Z")
PX4_PARAMETERS = ("EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_EV_POS_X", "EKF2_EV_POS_Y",
                  "EKF2_EV_POS_Z")
# ArduPilot's EK3_SRCn_* source numbers
EK3_SOURCES = {0: "none", 1: "baro", 2: "range finder", 3: "GPS", 4: "beacon", 5: "optical flow",
               6: "ExternalNav", 7: "wheel encoder", 8: "GSF"}
EK3_YAW_SOURCES = {0: "none", 1: "compass", 2: "GPS", 3: "GPS with compass fallback", 6: "ExternalNav",
                   8: "GSF"}
EXTERNAL_NAV = 6
PX4_HEIGHT_REFERENCES = {0: "baro", 1: "GPS", 2: "range finder", 3: "vision"}
# EKF2_EV_CTRL bits
EV_HORIZONTAL, EV_VERTICAL, EV_VELOCITY, EV_YAW = 1, 2, 4, 8
OFFSET_TOLERANCE_M = 0.005
MAX_DELAY_MS = 250.0  # VISO_DELAY_MS and EKF2_EV_DELAY ranges end here


@dataclass(frozen=True)
class Expected:
    """What the daemon sends, to judge the parameters against.

    lever_arm_m: the camera's optical centre in body FRD (the daemon sends the
    body origin, this already applied); None when not known. sends_velocity:
    VISION_SPEED_ESTIMATE or ODOMETRY is sent. latency_ms: the measured median
    capture -> send latency (None: not measured).
    """

    lever_arm_m: tuple[float, float, float] | None = None
    sends_velocity: bool = False
    latency_ms: float | None = None


@dataclass(frozen=True)
class ParameterCheck:
    """One parameter's value (None: the FC did not report it), what we want, and the verdict with its reason."""

    name: str
    value: float | None
    expected: str
    verdict: str
    why: str = ""

    def value_text(self) -> str:
        if self.value is None:
            return "-"
        return f"{self.value:g}"


def parameter_names(autopilot: int | None) -> tuple[str, ...]:
    """The parameters to read from this autopilot (none for one we do not know)."""
    return {ARDUPILOT: ARDUPILOT_PARAMETERS, PX4: PX4_PARAMETERS}.get(autopilot, ())


def check_parameters(autopilot: int | None, values: dict[str, float | None], expected: Expected) -> list[ParameterCheck]:
    """Each parameter of ``parameter_names(autopilot)`` judged; values missing from ``values`` count as unreported."""
    if autopilot == ARDUPILOT:
        return _ardupilot(values, expected)
    if autopilot == PX4:
        return _px4(values, expected)
    return []


def blocking(checks: list[ParameterCheck]) -> list[ParameterCheck]:
    return [c for c in checks if c.verdict == BLOCKS]


def problems(checks: list[ParameterCheck]) -> list[ParameterCheck]:
    return [c for c in checks if c.verdict != OK]


def _unreported(name: str, expected: str) -> ParameterCheck:
    return ParameterCheck(name, None, expected, DEGRADES, "not reported by the flight controller")


def _ardupilot(values: dict, expected: Expected) -> list[ParameterCheck]:
    checks = []
    v = values.get("AHRS_EKF_TYPE")
    checks.append(_unreported("AHRS_EKF_TYPE", "3") if v is None else
                  ParameterCheck("AHRS_EKF_TYPE", v, "3", OK if v == 3 else BLOCKS,
                                 "" if v == 3 else f"EKF{v:g} selected: vision is fused by EKF3"))
    v = values.get("VISO_TYPE")
    want = "1 (MAVLink)"
    if v is None:
        checks.append(ParameterCheck("VISO_TYPE", None, want, BLOCKS,
                                     "not reported: firmware built without visual odometry?"))
    elif v == 1:
        checks.append(ParameterCheck("VISO_TYPE", v, want, OK))
    elif v == 0:
        checks.append(ParameterCheck("VISO_TYPE", v, want, BLOCKS, "visual odometry is off"))
    else:
        checks.append(ParameterCheck("VISO_TYPE", v, want, DEGRADES,
                                     "types 2/3 re-align yaw to the autopilot's at start: wrong for an absolute map"))
    checks.append(_source("EK3_SRC1_POSXY", values, EK3_SOURCES, BLOCKS, "horizontal position from {}, not vision"))
    checks.append(_source("EK3_SRC1_POSZ", values, EK3_SOURCES, DEGRADES, "height from {}, not vision"))
    v = values.get("EK3_SRC1_YAW")
    if v == 1:
        checks.append(ParameterCheck("EK3_SRC1_YAW", v, "6 (ExternalNav)", DEGRADES,
                                     "compass yaw: right only with a surveyed map heading and a compass that "
                                     "works indoors"))
    else:
        checks.append(_source("EK3_SRC1_YAW", values, EK3_YAW_SOURCES, BLOCKS if v == 0 else DEGRADES,
                              "yaw from {}, not vision"))
    checks.append(_velocity_source(values.get("EK3_SRC1_VELXY"), expected.sends_velocity))
    checks.append(_delay("VISO_DELAY_MS", values.get("VISO_DELAY_MS"), expected.latency_ms))
    checks += _offsets(("VISO_POS_X", "VISO_POS_Y", "VISO_POS_Z"), values, expected.lever_arm_m)
    return checks


def _source(name: str, values: dict, names: dict, verdict: str, why: str) -> ParameterCheck:
    """An EK3_SRC1_* parameter that should be ExternalNav (6)."""
    want = f"{EXTERNAL_NAV} (ExternalNav)"
    v = values.get(name)
    if v is None:
        return _unreported(name, want)
    if v == EXTERNAL_NAV:
        return ParameterCheck(name, v, want, OK)
    return ParameterCheck(name, v, want, verdict, why.format(names.get(int(v), f"source {v:g}")))


def _velocity_source(v: float | None, sends_velocity: bool) -> ParameterCheck:
    name = "EK3_SRC1_VELXY"
    if sends_velocity:
        want = f"{EXTERNAL_NAV} (ExternalNav: VISION_SPEED_ESTIMATE is sent)"
        if v is None:
            return _unreported(name, want)
        return ParameterCheck(name, v, want, OK if v == EXTERNAL_NAV else DEGRADES,
                              "" if v == EXTERNAL_NAV else "the velocity we send is not used")
    want = "0 (no velocity is sent)"
    if v is None:
        return _unreported(name, want)
    if v == EXTERNAL_NAV:
        return ParameterCheck(name, v, want, DEGRADES, "ExternalNav velocity expected, but the config sends "
                                                       "no VISION_SPEED_ESTIMATE")
    if v == 0:
        return ParameterCheck(name, v, want, OK)
    return ParameterCheck(name, v, want, DEGRADES, f"velocity from {EK3_SOURCES.get(int(v), f'source {v:g}')}")


def _delay(name: str, v: float | None, latency_ms: float | None) -> ParameterCheck:
    """The autopilot's vision delay against the measured capture -> send latency."""
    if latency_ms is None:
        want = "the measured capture->send latency (ms)"
    else:
        # nearest 5 ms above the measured latency (exposure and transport add a little)
        want = f"{5 * math.ceil(latency_ms / 5):g} (measured {latency_ms:.0f} ms)"
    if v is None:
        return _unreported(name, want)
    if not 0 < v <= MAX_DELAY_MS:
        return ParameterCheck(name, v, want, DEGRADES, f"outside 1..{MAX_DELAY_MS:g} ms: samples are fused at the "
                                                       "wrong time")
    # off by more than 10 ms or half the latency: the EKF fuses each pose against the wrong past state
    if latency_ms is not None and abs(v - latency_ms) > max(10.0, 0.5 * latency_ms):
        return ParameterCheck(name, v, want, DEGRADES, f"{v - latency_ms:+.0f} ms from the measured latency")
    return ParameterCheck(name, v, want, OK)


def _offsets(names: tuple[str, str, str], values: dict, lever_arm_m) -> list[ParameterCheck]:
    """Sensor offsets should be 0: the daemon sends the body origin (the lever arm already applied)."""
    checks = []
    for axis, name in enumerate(names):
        v = values.get(name)
        if v is None:
            checks.append(_unreported(name, "0"))
        elif abs(v) < OFFSET_TOLERANCE_M:
            checks.append(ParameterCheck(name, v, "0", OK))
        elif lever_arm_m is not None and abs(v - lever_arm_m[axis]) < OFFSET_TOLERANCE_M:
            checks.append(ParameterCheck(name, v, "0", DEGRADES, "the camera's lever arm again: applied twice "
                                                                 "(the daemon sends the body origin)"))
        else:
            checks.append(ParameterCheck(name, v, "0", DEGRADES, f"{v:g} m offset: the daemon already sends the "
                                                                 "body origin"))
    return checks


def _px4(values: dict, expected: Expected) -> list[ParameterCheck]:
    checks = []
    want = "15 (position, height, velocity, yaw)" if expected.sends_velocity else "11 (position, height, yaw)"
    v = values.get("EKF2_EV_CTRL")
    if v is None:
        checks.append(_unreported("EKF2_EV_CTRL", want))
    else:
        bits = int(v)
        missing = [what for bit, what in ((EV_VERTICAL, "height"), (EV_YAW, "yaw")) if not bits & bit]
        if not bits & EV_HORIZONTAL:
            checks.append(ParameterCheck("EKF2_EV_CTRL", v, want, BLOCKS, "horizontal position from vision not fused"))
        elif missing:
            checks.append(ParameterCheck("EKF2_EV_CTRL", v, want, DEGRADES, f"vision {' and '.join(missing)} not fused"))
        else:
            checks.append(ParameterCheck("EKF2_EV_CTRL", v, want, OK))
    v = values.get("EKF2_HGT_REF")
    if v is None:
        checks.append(_unreported("EKF2_HGT_REF", "3 (vision)"))
    else:
        checks.append(ParameterCheck("EKF2_HGT_REF", v, "3 (vision)", OK if v == 3 else DEGRADES,
                                     "" if v == 3 else f"height from {PX4_HEIGHT_REFERENCES.get(int(v), v)}"))
    checks.append(_delay("EKF2_EV_DELAY", values.get("EKF2_EV_DELAY"), expected.latency_ms))
    checks += _offsets(("EKF2_EV_POS_X", "EKF2_EV_POS_Y", "EKF2_EV_POS_Z"), values, expected.lever_arm_m)
    return checks


def statustexts(checks: list[ParameterCheck], prefix: str = "companion: ") -> list[tuple[str, int]]:
    """The problems of ``checks`` as (text, MAV_SEVERITY), each text at most STATUSTEXT_MAX_CHARS:
    the blocking ones, all of them, by name and value ("VISO_TYPE=0 blocks vision", CRITICAL; by name
    alone when that takes fewer texts: "AHRS_EKF_TYPE, VISO_TYPE block vision");
    then one text for those that degrade vision ("VISO_POS_X=0.1, +2 degrade vision", WARNING) and
    one for those the FC did not report ("FC did not report 9 params", WARNING). The log has the reasons.
    """
    blocks = [c for c in checks if c.verdict == BLOCKS]
    degrades = [f"{c.name}={c.value_text()}" for c in checks if c.verdict == DEGRADES and c.value is not None]
    unreported = [c for c in checks if c.verdict == DEGRADES and c.value is None]
    width = STATUSTEXT_MAX_CHARS - len(prefix)
    with_values = _packed([f"{c.name}={'?' if c.value is None else c.value_text()}" for c in blocks],
                          "blocks", "block", width)
    names_only = _packed([c.name for c in blocks], "blocks", "block", width)
    texts = [(prefix + text, SEVERITY_CRITICAL)
             for text in (with_values if len(with_values) <= len(names_only) else names_only)]
    texts += [(prefix + text, SEVERITY_WARNING) for text in _packed(degrades, "degrades", "degrade", width, 1)]
    if unreported:
        texts.append((f"{prefix}FC did not report {len(unreported)} param{'s' * (len(unreported) > 1)}",
                      SEVERITY_WARNING))
    return texts


def _packed(items: list[str], verb_one: str, verb_many: str, width: int, max_texts: int | None = None) -> list[str]:
    """``items`` in as few texts of at most ``width`` characters as carry them ("A=1, B=3 block vision");
    with ``max_texts``, the last one ends with how many did not fit ("A=1, +3 degrade vision")."""
    texts, rest = [], list(items)
    while rest and (max_texts is None or len(texts) < max_texts):
        last = max_texts is not None and len(texts) == max_texts - 1
        for count in range(len(rest), 0, -1):
            left = len(rest) - count if last else 0
            names = ", ".join(rest[:count] + ([f"+{left}"] if left else []))
            text = f"{names} {verb_one if count + left == 1 else verb_many} vision"
            if len(text) <= width or count == 1:
                break
        texts.append(text[:width])
        rest = rest[count:] if not last else []
    return texts


def table(checks: list[ParameterCheck]) -> str:
    """The checks as a fixed-width table: parameter, value, expected, verdict, why."""
    rows = [("parameter", "value", "expected", "verdict", "why")]
    rows += [(c.name, c.value_text(), c.expected, c.verdict.upper() if c.verdict == BLOCKS else c.verdict, c.why)
             for c in checks]
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "".join(("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + row[4]).rstrip() + "\n"
                   for row in rows)
