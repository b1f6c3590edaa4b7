"""Plain TOML data mapped onto configuration dataclasses, with errors that name the key."""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from typing import Any

from slscan.errors import SlscanError


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise SlscanError(f"{where}: expected a table of {tp.__name__} settings, got {value!r}")
        return from_mapping(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        errors = []
        for option in options:
            try:
                return _convert(option, value, where)
            except SlscanError as exc:
                errors.append(str(exc))
        raise SlscanError(errors[0] if len(errors) == 1 else f"{where}: {value!r} fits none of {tp}")
    if tp is bool:
        if not isinstance(value, bool):
            raise SlscanError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SlscanError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SlscanError(f"{where}: expected a number, got {value!r}")
        number = float(value) if isinstance(value, float) or abs(value) < 2**1000 else math.inf
        if not math.isfinite(number):
            raise SlscanError(f"{where}: expected a finite number, got {value!r}")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise SlscanError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is dict or origin is dict:
        if not isinstance(value, Mapping):
            raise SlscanError(f"{where}: expected a table, got {value!r}")
        return dict(value)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise SlscanError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise SlscanError(f"{where}: expected a list of {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    raise SlscanError(f"{where}: settings of type {_type_name(tp)} cannot be given in a recipe")


def from_mapping(cls: type, data: Mapping[str, Any], where: str) -> Any:
    """Build dataclass ``cls`` from ``data``; unknown keys and wrong types raise naming the key."""
    hints = typing.get_type_hints(cls)
    settable = {f.name: f for f in dataclasses.fields(cls) if f.init}
    for key in data:
        if key not in settable:
            raise SlscanError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(settable))})")
    kwargs = {name: _convert(hints[name], data[name], f"{where}.{name}") for name in data}
    try:
        return cls(**kwargs)
    except SlscanError as exc:  # a check of the dataclass; "KEY: why" names the key
        key, sep, why = str(exc).partition(": ")
        if sep and key in settable:
            raise SlscanError(f"{where}.{key}: {why}") from None
        raise SlscanError(f"{where}: {exc}") from None


def to_mapping(obj: Any) -> dict[str, Any]:
    """Plain data (dicts, lists, scalars) of a configuration dataclass, for TOML and hashing.

    Settings that are None (TOML has no null) are left out: absent means the default.
    """

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)
                    if f.init and getattr(value, f.name) is not None}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(obj)


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"decode.estimator=centroid"`` → (["decode", "estimator"], "centroid").

    The value is read as a TOML value (numbers, booleans, quoted strings, lists); anything
    that is not valid TOML is taken as a plain string.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise SlscanError(f"--set {text!r}: expected KEY=VALUE, e.g. capture.views=4")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return [k.strip() for k in key.split(".")], value


def set_in(data: dict[str, Any], path: list[str], value: Any) -> None:
    for part in path[:-1]:
        node = data.setdefault(part, {})
        if not isinstance(node, dict):
            raise SlscanError(f"--set {'.'.join(path)}: {part!r} is a value, not a table")
        data = node
    data[path[-1]] = value


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if value is None:
        raise SlscanError("TOML has no null value")
    raise SlscanError(f"cannot write {type(value).__name__} to TOML")


def dumps_toml(data: Mapping[str, Any]) -> str:
    """A small TOML writer for nested tables of scalars and lists (what recipes hold)."""
    lines: list[str] = []

    def table(prefix: str, node: Mapping[str, Any]) -> None:
        scalars = {k: v for k, v in node.items() if not isinstance(v, Mapping) and v is not None}
        tables = {k: v for k, v in node.items() if isinstance(v, Mapping)}
        if prefix and (scalars or not tables):
            lines.append(f"\n[{prefix}]")
        for k, v in scalars.items():
            key = k if k.replace("_", "").replace("-", "").isalnum() else _toml_value(k)
            lines.append(f"{key} = {_toml_value(v)}")
        for k, v in tables.items():
            table(f"{prefix}.{k}" if prefix else k, v)

    table("", data)
    return "\n".join(lines).lstrip("\n") + "\n"
