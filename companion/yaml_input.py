"""YAML input files: reading one, and naming the place in it that is wrong.

``read_yaml`` gives a file's top-level mapping; ``Where`` is a file and a
dotted key path whose ``error`` builds the calling module's own ValueError
subclass (ConfigError, MapError, CameraError), plus the checks the config,
map and camera readers share. A message names the key in one of three styles
(each module's messages are documented and tested as they stand):

- ``"dotted"``: ``config.yaml: source.kind: must be one of ...``
- ``"quoted"``: ``drone.yaml: key 'camera.width': ...`` (``section 'camera'`` without a key)
- ``"labelled"``: ``hall.yaml: markers entry 8 (H): key 'size_m': ...``
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

REQUIRED = object()  # the default of a key that must be given


class _InputLoader(yaml.SafeLoader):
    """PyYAML's safe loader, stricter and kinder: a key given twice in one mapping is an error (PyYAML keeps
    the last and drops the first without a word: a second ``markers:`` would delete the first list), and
    ``1e9`` or ``2e-1`` are numbers (YAML 1.1, which PyYAML follows, wants a dot: ``1.0e9``)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # "<<: *defaults": its keys may be given again, that is what it is for
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, (str, int, float, bool)):
                if key in seen:
                    raise yaml.constructor.ConstructorError("while reading a mapping", node.start_mark,
                                                            f"key {key!r} given twice", key_node.start_mark)
                seen.add(key)
        return super().construct_mapping(node, deep)


# YAML 1.1's floats, and numbers with an exponent but no dot (1e9, -2E-3)
_InputLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"),
                                   list("-+0123456789"))


def read_yaml(path, error_type: type[ValueError], what: str) -> dict:
    """The top-level mapping of a YAML file (empty for an empty file), e.g. ``what="map"``.

    Raises ``error_type`` naming the file when it cannot be read, is not
    valid YAML (with line and column) or holds something other than a mapping.
    """
    where = Where(str(path), error_type)
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise where.error(f"cannot read {what}: {getattr(error, 'strerror', None) or error}") from None
    try:
        data = yaml.load(text, Loader=_InputLoader)
    except yaml.YAMLError as error:
        raise where.error(f"not valid YAML: {_one_line(error)}") from None
    return where.mapping(data, f"the {what}")


def _one_line(error: yaml.YAMLError) -> str:
    """The parser's complaint on one line, with where it is and what it was parsing."""
    mark, context_mark = getattr(error, "problem_mark", None), getattr(error, "context_mark", None)
    if mark is None:
        return str(error)
    text = f"line {mark.line + 1}, column {mark.column + 1}: {error.problem}"
    if context_mark is not None:
        text += f" ({error.context} at line {context_mark.line + 1}, column {context_mark.column + 1})"
    return text


@dataclass(frozen=True)
class Where:
    """A section of an input file: ``file``, its dotted key path ``section``, the module's error type."""

    file: str
    error_type: type[ValueError]
    section: str = ""
    style: Literal["dotted", "quoted", "labelled"] = "dotted"

    def sub(self, name: str) -> Where:
        return dataclasses.replace(self, section=_dotted(self.section, name))

    def error(self, message: str, key: str | None = None) -> ValueError:
        """The module's error: ``file: place: message``, the place being this section or its ``key``."""
        place = _dotted(self.section, key)
        if self.style == "quoted" and place:
            place = f"{'key' if key else 'section'} '{place}'"
        elif self.style == "labelled" and key:
            place = ": ".join(filter(None, (self.section, f"key '{key}'")))
        return self.error_type(f"{self.file}: {place}: {message}" if place else f"{self.file}: {message}")

    def mapping(self, value, what: str) -> dict:
        """``value`` itself if it is a mapping (``what`` lists its keys), empty for null."""
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(f"must be a mapping ({what}), got {type(value).__name__}")
        return value

    def reject_unknown(self, mapping: dict, known: set[str]) -> None:
        unknown = sorted(str(key) for key in mapping if key not in known)
        if unknown:
            raise self.error(f"unknown key '{unknown[0]}' (known keys: {', '.join(sorted(known))})", unknown[0])

    def value(self, mapping: dict, key: str, default=REQUIRED):
        """``mapping[key]``; ``default`` when it is absent or null ("missing" if there is none)."""
        value = mapping.get(key)
        if value is not None:
            return value
        if default is REQUIRED:
            raise self.error("missing", key)
        return default

    def number(self, mapping: dict, key: str, default=REQUIRED, minimum: float | None = None) -> float | None:
        """``mapping[key]`` as a finite float >= ``minimum``; None for an absent key with default None."""
        value = self.value(mapping, key, default)
        if value is None:
            return None
        number = self._finite(value, key)
        if minimum is not None and number < minimum:
            raise self.error(f"must be >= {minimum:g}, got {value!r}", key)
        return number

    def positive(self, mapping: dict, key: str, default=REQUIRED, integer: bool = False) -> float | int | None:
        """``mapping[key]`` > 0, as an int when ``integer``; None for an absent key with default None."""
        number = self.number(mapping, key, default)
        if number is None:
            return None
        if integer and (number <= 0 or not number.is_integer()):
            raise self.error(f"must be a positive integer, got {number:g}", key)
        if number <= 0:
            raise self.error(f"must be positive, got {number:g}", key)
        return int(number) if integer else number

    def numbers(self, mapping: dict, key: str, lengths: tuple[int, ...], default=REQUIRED,
                meaning: str = "") -> np.ndarray:
        """(n,) floats of ``mapping[key]``, a list of n finite numbers, n in ``lengths``."""
        values = self.value(mapping, key, default)
        if not isinstance(values, (list, tuple)) or len(values) not in lengths:
            count = ", ".join(map(str, lengths))
            raise self.error(f"must be a list of {count} numbers{meaning}, got {values!r}", key)
        return np.array([self._finite(value, key) for value in values])

    def flag(self, mapping: dict, key: str, default: bool) -> bool:
        value = self.value(mapping, key, default)
        if not isinstance(value, bool):
            raise self.error(f"must be true or false, got {value!r}", key)
        return value

    def path(self, mapping: dict, key: str) -> Path:
        """``mapping[key]`` as a path; a relative one is taken from the folder of this file."""
        value = self.value(mapping, key)
        if not isinstance(value, str) or not value:
            raise self.error(f"must be a path, got {value!r}", key)
        path = Path(value).expanduser()
        return path if path.is_absolute() else Path(self.file).resolve().parent / path

    def _finite(self, value, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(f"must be a finite number, got {value!r}", key)
        return float(value)


def _dotted(section: str, key: str | None) -> str:
    return ".".join(filter(None, (section, key)))
