"""Parameter dataclasses: range checks that name the parameter, and building one from a (YAML) mapping.

A stage's settings are a frozen dataclass whose fields carry their unit in
their name and their one default; its ``__post_init__`` calls ``require``
for each range. ``from_mapping`` builds such a dataclass, nested ones
included, from a plain mapping (a config section), checking keys and types
first, so every error names the dotted key it is about::

    ParamsError: circles.min_area_px: must be >= 1, got 0
"""
from __future__ import annotations

import dataclasses
import math


class ParamsError(ValueError):
    """A parameter with a wrong value, type or name; ``key`` is its dotted name, ``reason`` what is wrong."""

    def __init__(self, key: str, reason: str):
        super().__init__(f"{key}: {reason}")
        self.key = key
        self.reason = reason

    def within(self, section: str) -> ParamsError:
        """The same error, its key prefixed by the enclosing section."""
        return ParamsError(f"{section}.{self.key}" if section else self.key, self.reason)


def require(ok: bool, key: str, requirement: str, value) -> None:
    """Raise ``ParamsError`` for ``key`` unless ``ok``: "must be <requirement>, got <value>"."""
    if not ok:
        raise ParamsError(key, f"must be {requirement}, got {value!r}")


def from_mapping(params_type: type, mapping, section: str = ""):
    """An instance of the dataclass ``params_type`` from a mapping of (some of) its fields.

    Nested dataclass fields take nested mappings; a list is taken for a tuple
    field; an int for a float field. Unknown keys, wrong types and values out
    of range raise ``ParamsError`` with the dotted key (prefixed by ``section``).
    """
    if mapping is None:
        mapping = {}
    if not isinstance(mapping, dict):
        raise ParamsError(section or "parameters", f"must be a mapping, got {type(mapping).__name__}")
    fields = {f.name: f for f in dataclasses.fields(params_type)}
    values = {}
    for key, value in mapping.items():
        dotted = f"{section}.{key}" if section else str(key)
        if key not in fields:
            raise ParamsError(dotted, f"unknown key (known keys: {', '.join(sorted(fields))})")
        default = _default(fields[key])
        if dataclasses.is_dataclass(default):
            values[key] = from_mapping(type(default), value, dotted)
        else:
            values[key] = _typed(value, default, dotted)
    try:
        return params_type(**values)
    except ParamsError as error:
        raise error.within(section) from None


def _default(field: dataclasses.Field):
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return field.default


def _typed(value, default, key: str):
    """``value`` checked against the type of the field's default."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ParamsError(key, f"must be true or false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamsError(key, f"must be an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ParamsError(key, f"must be a finite number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ParamsError(key, f"must be a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise ParamsError(key, f"must be a list of {len(default)} values, got {value!r}")
        return tuple(_typed(v, d, key) for v, d in zip(value, default))
    return value  # no default to compare with: the dataclass checks it
