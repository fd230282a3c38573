"""A small validator for TOML tables: known keys, types, ranges, defaults, one-line errors.

Rig configs, plans and excitations are all plain tables; validating them here gives every bad
value the same kind of message: the file, the table and key, what was expected and what was found.
"""

from __future__ import annotations

import difflib
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hilbench.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass(frozen=True)
class Key:
    """One key of a table.

    kind: ``number``, ``int``, ``str``, ``bool``, ``numbers`` (list of numbers), ``strs``,
    ``table``, ``tables`` (list of tables), ``pair`` (two numbers ``[low, high]``),
    ``number-or-numbers``, ``any``.
    """

    kind: str
    required: bool = False
    default: Any = None
    choices: tuple[Any, ...] = ()
    minimum: float | None = None
    exclusive_minimum: bool = False
    maximum: float | None = None
    doc: str = ""


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _expected(key: Key) -> str:
    names = {
        "number": "a finite number",
        "int": "an integer",
        "str": "a string",
        "bool": "true or false",
        "numbers": "a list of numbers",
        "strs": "a list of strings",
        "table": "a table",
        "tables": "a list of tables",
        "pair": "two numbers [low, high]",
        "number-or-numbers": "a number or a list of numbers",
        "any": "a value",
    }
    text = names[key.kind]
    if key.choices:
        text = "one of " + ", ".join(repr(c) for c in key.choices)
    if key.minimum is not None:
        text += f" {'>' if key.exclusive_minimum else '>='} {key.minimum:g}"
    if key.maximum is not None:
        text += f" <= {key.maximum:g}"
    return text


def _type_ok(kind: str, value: Any) -> bool:
    if kind == "number":
        return _is_number(value)
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "str":
        return isinstance(value, str)
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "numbers":
        return isinstance(value, list) and all(_is_number(v) for v in value)
    if kind == "strs":
        return isinstance(value, list) and all(isinstance(v, str) for v in value)
    if kind == "table":
        return isinstance(value, Mapping)
    if kind == "tables":
        return isinstance(value, list) and all(isinstance(v, Mapping) for v in value)
    if kind == "pair":
        return isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value)
    if kind == "number-or-numbers":
        return _is_number(value) or _type_ok("numbers", value)
    return True


def _range_ok(key: Key, value: Any) -> bool:
    values: list[Any]
    if key.kind in ("number", "int"):
        values = [value]
    elif key.kind in ("numbers", "pair", "number-or-numbers"):
        values = value if isinstance(value, list) else [value]
    else:
        values = []
    for v in values:
        if key.minimum is not None and (v < key.minimum or (key.exclusive_minimum and v == key.minimum)):
            return False
        if key.maximum is not None and v > key.maximum:
            return False
    return True


def check_table(
    data: Mapping[str, Any],
    schema: Mapping[str, Key],
    *,
    file: str,
    table: str,
    extra_check: Callable[[dict[str, Any]], str | None] | None = None,
) -> dict[str, Any]:
    """Validate ``data`` against ``schema``; return a copy with defaults filled in.

    Raises :class:`ConfigError` naming the file, ``[table] key``, what was expected and what was found.
    """
    where_table = f"[{table}]" if table else "top level"
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where_table}: expected a table, got {_describe(data)}", where=file)
    unknown = [k for k in data if k not in schema]
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), list(schema), n=1, cutoff=0.6)
        raise ConfigError(
            f"{where_table}: unknown key {unknown[0]!r}; expected one of: {', '.join(schema)}", where=file,
            hint=f"did you mean {close[0]!r}?" if close else "remove it, or check the spelling against the keys listed",
        )
    out: dict[str, Any] = {}
    for name, key in schema.items():
        if name not in data:
            if key.required:
                raise ConfigError(f"{where_table}: missing key {name!r} ({_expected(key)})", where=file,
                                  hint=f"add {name} = ... to {where_table}" + (f" ({key.doc})" if key.doc else ""))
            out[name] = key.default
            continue
        value = data[name]
        if key.kind == "number" and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not _type_ok(key.kind, value) or (key.choices and value not in key.choices) or not _range_ok(key, value):
            raise ConfigError(
                f"{where_table} {name}: expected {_expected(key)}, got {_describe(value)}", where=file
            )
        out[name] = value
    if extra_check is not None:
        problem = extra_check(out)
        if problem:
            raise ConfigError(f"{where_table}: {problem}", where=file)
    return out


def parse_scalar(text: str) -> Any:
    """A command-line value: int, float, true/false, or the text itself."""
    text = text.strip()
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    return text


def read_toml(path: Path) -> tuple[str, dict[str, Any]]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("file not found", where=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read ({exc.__class__.__name__}: {exc})", where=str(path)) from None
    try:
        return text, tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}", where=str(path)) from None
