"""Settings declared once: each dataclass field carries its default, unit, range and doc, and the
readers validate a YAML value against that declaration; the primitive checks name the field path.

A setting is a dataclass field whose metadata is :func:`spec`, e.g. ``rate_hz: float = field(default=30.0,
metadata=spec("...", unit="Hz", within="[1, 200]"))``; :func:`read` reads
one such field from a YAML mapping (its default when absent, its range checked), and :func:`defaults`
gives a class's declared defaults for code that needs one without a config (no literal repeated).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Mapping
from enum import Enum
from functools import cache
from pathlib import Path
from typing import Any

from atlas_onboard.errors import ConfigError

REQUIRED = dataclasses.MISSING
"""The default of a setting that has none: the reader requires it."""


def spec(
    doc: str,
    *,
    unit: str = "",
    within: str = "",
    noun: str = "a value",
    choices: tuple[str, ...] = (),
    off: float | None = None,
    paper: Any = REQUIRED,
    key: str | None = None,
    fallback: str = "",
) -> dict[str, Any]:
    """The declaration of a setting, the ``metadata`` of its dataclass field (whose default is its default).

    ``doc`` says what it means, ``unit`` its unit; ``within`` bounds a number, ``"[lo, hi]"`` or
    ``"(lo, hi]"`` (lo excluded), ``noun`` names it in a range error ("expected a timeout in (0, 10] s"), ``off`` is a
    value allowed outside the range that turns the feature off, ``choices`` the strings allowed,
    ``paper`` the paper's value (fusion settings), ``key`` the YAML key when it is not the field's
    name, ``fallback`` the setting whose value an optional key without a default of its own takes.
    """
    lo = hi = None
    if within:
        lo_text, hi_text = within[1:-1].split(",")
        lo, hi = float(lo_text), float(hi_text)
    return {
        "doc": doc, "unit": unit, "within": within, "lo": lo, "hi": hi, "lo_open": within.startswith("("), "noun": noun,
        "choices": choices, "off": off, "paper": paper, "key": key, "fallback": fallback,
    }  # fmt: skip


def declared(cls: type) -> dict[str, dataclasses.Field[Any]]:
    """The fields of ``cls`` declared with :func:`spec`, by name, in declaration order."""
    return {f.name: f for f in dataclasses.fields(cls) if "doc" in f.metadata}


def required(cls: type) -> set[str]:
    """The YAML keys of the settings of ``cls`` that must be given (no default, no fallback)."""
    return {
        f.metadata["key"] or n for n, f in declared(cls).items() if f.default is REQUIRED and not f.metadata["fallback"]
    }


def defaults(cls: type) -> dict[str, Any]:
    """The declared default of every setting of ``cls`` that has one."""
    return {n: f.default for n, f in declared(cls).items() if f.default is not REQUIRED}


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def kind_of(cls: type, name: str) -> type:
    """The value type a setting reads: bool, int, float, str, Path or an Enum (Optional unwrapped)."""
    hint = _hints(cls)[name]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if args and typing.get_origin(hint) is not None else hint


def range_text(meta: Mapping[str, Any]) -> str:
    """The declared interval of a number, ``(0, 10]``-style, or "" without one."""
    return str(meta["within"])


def read(cls: type, name: str, m: Mapping[str, Any], path: str, default: Any = REQUIRED) -> Any:
    """Setting ``name`` of ``cls`` from mapping ``m`` (at ``path``), checked against its declaration;
    absent, ``default`` if given, else the declared default (a required setting must be present)."""
    f = declared(cls)[name]
    key = f.metadata["key"] or name
    here = join(path, key)
    if key not in m:
        value = f.default if default is REQUIRED else default
        if value is REQUIRED:
            raise ConfigError(here, "missing required field")
        return value
    return check(cls, name, m[key], here)


def check(cls: type, name: str, value: Any, path: str) -> Any:
    """``value`` as setting ``name`` of ``cls``: its type, choices and range checked."""
    f = declared(cls)[name]
    meta, kind = f.metadata, kind_of(cls, name)
    if kind is bool:
        return boolean(value, path)
    if isinstance(kind, type) and issubclass(kind, Enum):
        return kind(choice(value, path, tuple(e.value for e in kind)))
    if kind is str:
        return choice(value, path, meta["choices"]) if meta["choices"] else string(value, path)
    if kind is Path:
        return Path(string(value, path))
    if kind is int:
        lo, hi = meta["lo"], meta["hi"]
        return integer(value, path, int(lo), int(hi))
    if kind is not float:
        raise TypeError(f"{cls.__name__}.{name}: a {kind} is read by its section's reader, not by check()")
    x = number(value, path, meta["unit"])
    lo, hi = meta["lo"], meta["hi"]
    inside = lo is None or ((lo < x if meta["lo_open"] else lo <= x) and x <= hi)
    if not inside and x != meta["off"]:
        unit = f" {meta['unit']}" if meta["unit"] else ""
        off = f"{meta['off']:g} (off) or " if meta["off"] is not None else ""
        raise ConfigError(path, f"expected {off}{meta['noun']} in {range_text(meta)}{unit}, got {x}")
    return x


# --- primitive checks: each names the path of what it reads ----------------------------------------------


def join(path: str, key: str | int) -> str:
    """``path.key``, or ``path[key]`` for a list index."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def mapping(value: Any, path: str, allowed: set[str], required: set[str] = frozenset()) -> Mapping[str, Any]:  # type: ignore[assignment]
    """``value`` as a mapping with only ``allowed`` string keys and every ``required`` one."""
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"expected a mapping, got {describe(value)}")
    for key in value:
        if not isinstance(key, str):
            raise ConfigError(path, f"expected string keys, got {key!r}")
        if key not in allowed:
            match = difflib.get_close_matches(key, sorted(allowed), n=1)
            hint = f" (did you mean {match[0]!r}?)" if match else ""
            raise ConfigError(join(path, key), f"unknown key{hint} (allowed: {', '.join(sorted(allowed))})")
    for key in sorted(required):
        if key not in value:
            raise ConfigError(join(path, key), "missing required field")
    return value


def keys(cls: type) -> set[str]:
    """The YAML keys of the declared settings of ``cls``."""
    return {f.metadata["key"] or n for n, f in declared(cls).items()}


def describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    return f"{type(value).__name__} {value!r}" if not isinstance(value, (dict, list)) else type(value).__name__


def number(value: Any, path: str, unit: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(path, f"expected a number{unit and ' in ' + unit}, got {describe(value)}")
    if not math.isfinite(value):
        raise ConfigError(path, f"expected a finite number, got {value}")
    return float(value)


def integer(value: Any, path: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(path, f"expected an integer, got {describe(value)}")
    if not lo <= value <= hi:
        raise ConfigError(path, f"expected an integer in [{lo}, {hi}], got {value}")
    return value


def boolean(value: Any, path: str) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(path, f"expected true or false, got {describe(value)}")
    return value


def string(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(path, f"expected a string, got {describe(value)}")
    return value


def choice(value: Any, path: str, choices: tuple[str, ...]) -> str:
    text = string(value, path)
    if text not in choices:
        shown = ", ".join(c or '""' for c in choices)
        raise ConfigError(path, f"expected one of {shown}, got {text!r}")
    return text


def listing(value: Any, path: str) -> list[Any]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ConfigError(path, f"expected a list, got {describe(value)}")
    return value


def vector(value: Any, path: str, n: int) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise ConfigError(path, f"expected a list of {n} numbers, got {describe(value)}")
    return [number(v, join(path, i)) for i, v in enumerate(value)]
