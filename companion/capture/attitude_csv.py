"""``attitude.csv`` of a sequence folder: the flight controller's roll and pitch while it was recorded.

Format (one header line, then one row per sample, any rate, ``t_ns`` rising)::

    t_ns,roll_deg,pitch_deg
    0,0.412,-1.250
    20000000,0.398,-1.262

``t_ns`` is in the time base of the folder's ``timestamps.csv`` (the frames'
capture times); the angles are the body FRD frame relative to the local
level frame, Z-Y-X (3-2-1) Euler angles in degrees, as MAVLink's ATTITUDE
(``docs/frames.md``). Written by ``companion simulate`` (from the ground
truth) and by recordings of the daemon; read by replays and
``companion localize``. A folder without the file has no attitude.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

from companion.types import AttitudeSample

ATTITUDE_FILE = "attitude.csv"
COLUMNS = ("t_ns", "roll_deg", "pitch_deg")


class AttitudeFileError(ValueError):
    """An attitude.csv that cannot be read; the message names the file, the line and what is wrong."""


def read_attitude_csv(path) -> list[AttitudeSample]:
    """The samples of an attitude.csv (angles in radians)."""
    path = Path(path)
    try:
        with open(path, newline="") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None or tuple(h.strip() for h in header) != COLUMNS:
                raise AttitudeFileError(f"{path}: the header must be {','.join(COLUMNS)}, got {','.join(header or [])!r}")
            samples = [_sample(row, path, reader.line_num) for row in reader if row]
    except OSError as error:
        raise AttitudeFileError(f"{path}: cannot read: {error.strerror}") from None
    except (UnicodeDecodeError, csv.Error) as error:
        raise AttitudeFileError(f"{path}: cannot read ({error}): not an attitude table ({','.join(COLUMNS)})") from None
    for a, b in zip(samples, samples[1:]):
        if b.t_ns <= a.t_ns:
            raise AttitudeFileError(f"{path}: t_ns must rise from row to row ({a.t_ns} then {b.t_ns})")
    return samples


def _sample(row: list[str], path: Path, line: int) -> AttitudeSample:
    if len(row) != len(COLUMNS):
        raise AttitudeFileError(f"{path}: line {line}: want 3 values {','.join(COLUMNS)}, got {len(row)}")
    try:
        t_ns, roll_deg, pitch_deg = int(row[0]), float(row[1]), float(row[2])
    except ValueError:
        raise AttitudeFileError(f"{path}: line {line}: t_ns must be an integer and the angles numbers, "
                                f"got {','.join(row)!r}") from None
    if not (math.isfinite(roll_deg) and math.isfinite(pitch_deg) and abs(pitch_deg) <= 90.0):
        raise AttitudeFileError(f"{path}: line {line}: angles must be finite, pitch within +-90 degrees, "
                                f"got {','.join(row)!r}")
    return AttitudeSample(t_ns, math.radians(roll_deg), math.radians(pitch_deg))


def attitude_row(sample: AttitudeSample, t0_ns: int = 0) -> tuple:
    """One attitude.csv row of a sample, ``t_ns`` counted from ``t0_ns`` (micro-degrees: below a float32
    angle's resolution, so a recording replays what was used)."""
    return (int(sample.t_ns - t0_ns), f"{math.degrees(sample.roll_rad):.6f}", f"{math.degrees(sample.pitch_rad):.6f}")


class AttitudeCsvWriter:
    """Writes an attitude.csv sample by sample (a recording in progress); ``close()`` when done.

    Samples are ``AttitudeSample`` values (radians) whose ``t_ns`` is on the
    recording's time base (the one of its timestamps.csv).
    """

    def __init__(self, path):
        self.path = Path(path)
        self._handle = open(self.path, "w", newline="")
        self._writer = csv.writer(self._handle)
        self._writer.writerow(COLUMNS)

    def write(self, sample: AttitudeSample) -> None:
        self._writer.writerow(attitude_row(sample))

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> "AttitudeCsvWriter":
        return self

    def __exit__(self, *_) -> None:
        self.close()


def write_attitude_csv(path, samples) -> Path:
    """Write samples (``AttitudeSample``, radians) as attitude.csv; returns the path."""
    with AttitudeCsvWriter(path) as writer:
        for sample in samples:
            writer.write(sample)
    return Path(path)


def sequence_attitude(folder) -> list[AttitudeSample] | None:
    """The attitude of a sequence folder, or None when it has no attitude.csv."""
    path = Path(folder) / ATTITUDE_FILE
    return read_attitude_csv(path) if path.is_file() else None
