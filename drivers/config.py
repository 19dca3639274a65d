"""Strict TOML configuration: dataclasses describe each section, `load_section` checks a table
against one and names the key, the value and what is allowed when anything is off.

Declare bounds and choices with `spec`:

>>> from dataclasses import dataclass
>>> @dataclass
... class Serial:
...     port: str
...     baudrate: int = spec(921600, min=1)
>>> load_section(Serial, {"port": "/dev/ttyUSB0"}, "source").baudrate
921600
>>> load_section(Serial, {"port": "x", "baud": 9600}, "source")
Traceback (most recent call last):
...
fluxcal.drivers.errors.ConfigError: source.baud: unknown key (allowed: port, baudrate)
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Literal

from .errors import ConfigError
from .inputs import read_small

_MISSING = dataclasses.MISSING


def spec(default: Any = _MISSING, *, min: float | None = None, max: float | None = None,
         choices: tuple | None = None, length: int | None = None, doc: str = "",
         default_factory: Any = _MISSING) -> Any:
    """A dataclass field with validation metadata (bounds, choices, fixed list length)."""
    meta = {"min": min, "max": max, "choices": choices, "length": length, "doc": doc}
    if default_factory is not _MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    if isinstance(default, (list, dict)):
        value = default
        return dataclasses.field(default_factory=lambda: type(value)(value), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


#: the largest configuration file read (the examples in configs/ are 3.6 to 10 kB)
MAX_CONFIG_BYTES = 1 << 20


def read_toml(path: str | Path) -> dict:
    """Read a TOML file; a missing, malformed, oversized or non-regular file (a FIFO, /dev/zero) is a ConfigError
    naming it."""
    p = Path(path)
    data = read_small(p, "configuration file", MAX_CONFIG_BYTES, ConfigError,
                      f"larger than {MAX_CONFIG_BYTES >> 20} MiB (allowed: a configuration up to "
                      f"{MAX_CONFIG_BYTES >> 20} MiB): not a configuration file?")
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML: {e}") from None
    except RecursionError:
        raise ConfigError(f"{p}: not valid TOML: arrays or tables nested too deeply") from None


def load_section(cls: type, table: Any, path: str) -> Any:
    """Build dataclass `cls` from a TOML table, strictly."""
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: expected a table, got {_show(table)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            raise ConfigError(f"{path}.{key}: unknown key (allowed: {', '.join(fields)})")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, f in fields.items():
        key = f"{path}.{name}" if path else name
        if name not in table:
            if f.default is _MISSING and f.default_factory is _MISSING:
                raise ConfigError(f"{key}: required key is missing")
            continue
        kwargs[name] = _convert(hints[name], table[name], key, f.metadata)
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if check is not None:
        check(path)
    return obj


def _show(v: Any) -> str:
    """A value as TOML spells it, as the user wrote it: true (not Python's True), [1, false], a date as 2026-07-02;
    a string quoted, a table as "a table"."""
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return f"[{', '.join(_show(x) for x in v)}]"
    if isinstance(v, (datetime.date, datetime.time)):        # datetime.datetime is a date
        return v.isoformat()
    return repr(v)


def _convert(tp: Any, value: Any, key: str, meta: Any) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        errors = []
        for a in inner:
            try:
                return _convert(a, value, key, meta)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0])
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{key}: {_show(value)} is not allowed (allowed: {', '.join(map(repr, args))})")
        return value
    if origin in (list, tuple):
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {_show(value)}")
        length = meta.get("length") if meta else None
        if length is not None and len(value) != length:
            raise ConfigError(f"{key}: expected a list of {length} values, got {len(value)}")
        item_t = args[0] if args else Any
        inner_meta = {k: meta.get(k) for k in ("min", "max", "choices")} if meta else {}
        items = [_convert(item_t, v, f"{key}[{i}]", inner_meta) for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    if dataclasses.is_dataclass(tp):
        return load_section(tp, value, key)
    if tp is dict or origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a table, got {_show(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {_show(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected a whole number, got {_show(value)}")
        _bounds(value, key, meta)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {_show(value)}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number, got {_show(value)}")
        _bounds(value, key, meta)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {_show(value)}")
        choices = meta.get("choices") if meta else None
        if choices and value not in choices:
            raise ConfigError(f"{key}: {value!r} is not allowed (allowed: {', '.join(map(repr, choices))})")
        return value
    if tp is Any:
        return value
    raise TypeError(f"config field {key}: unsupported type {tp!r}")


def _bounds(value: float, key: str, meta: Any) -> None:
    if not meta:
        return
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None and value < lo:
        raise ConfigError(f"{key}: {value!r} is below the minimum {lo!r}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key}: {value!r} is above the maximum {hi!r}")
    choices = meta.get("choices")
    if choices and value not in choices:
        raise ConfigError(f"{key}: {value!r} is not allowed (allowed: {', '.join(map(repr, choices))})")
