"""Turn a config mapping (a ``params:`` entry of a rule) into a stage's typed config dataclass."""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from cystomap.errors import InputError

T = TypeVar("T")


def from_mapping(cls: type[T], mapping: Mapping[str, Any] | None, key: str) -> T:
    """Build dataclass ``cls`` from ``mapping``; ``key`` names the config section in errors.

    Unknown keys and values of the wrong type raise :class:`InputError` naming ``key.field``.
    Missing keys take the dataclass defaults. Lists become tuples where the field is a tuple.
    """
    mapping = dict(mapping or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise InputError(f"config {key}: unknown key(s) {', '.join(unknown)}; known: {', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for name, value in mapping.items():
        values[name] = _coerce(value, hints[name], f"{key}.{name}")
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise InputError(f"config {key}: {exc}") from exc


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except InputError as exc:
                errors.append(str(exc))
        raise InputError(errors[0] if errors else f"config {where}: bad value {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise InputError(f"config {where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(args) != len(value):
            raise InputError(f"config {where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"config {where}: expected a number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise InputError(f"config {where}: expected an integer, got {value!r}")
        return int(value)
    if hint is bool:
        if not isinstance(value, bool):
            raise InputError(f"config {where}: expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise InputError(f"config {where}: expected a string, got {value!r}")
        return value
    return value


# --------------------------------------------------------------------------- ranges

_BOUND = re.compile(r"^\s*(>=|>|<=|<)\s*(\S+)\s*$")
_INTERVAL = re.compile(r"^\s*([\[(])\s*(\S+)\s*,\s*(\S+)\s*([\])])\s*$")


def setting(default: Any, check: str | None = None, *, choices: Iterable[Any] | None = None) -> Any:
    """A config field: its default and, next to it, the values it accepts.

    ``check`` is a bound (``">= 16"``, ``"> 0"``) or an interval (``"[0, 1)"``, ``"(0, 255]"``);
    ``choices`` the allowed values. :func:`validate` (called from ``__post_init__``) enforces
    them, so a key's range is written once.
    """
    if check is not None:
        _parse_check(check)  # a typo fails at import time, not at the first bad config
    meta = {"check": check, "choices": tuple(choices) if choices is not None else None}
    return dataclasses.field(default=default, metadata=meta)


def _parse_check(check: str) -> tuple[tuple[str, float] | None, tuple[str, float] | None]:
    """(lower, upper) bounds of a check: (operator, value) or None."""
    m = _BOUND.match(check)
    if m:
        op, value = m.group(1), float(m.group(2))
        return ((op, value), None) if op in (">=", ">") else (None, (op, value))
    m = _INTERVAL.match(check)
    if not m:
        raise ValueError(f"bad range {check!r}: use '>= a', '> a', '<= b', '< b' or '[a, b)'")
    lo = (">=" if m.group(1) == "[" else ">", float(m.group(2)))
    hi = ("<=" if m.group(4) == "]" else "<", float(m.group(3)))
    return lo, hi


_OPS = {">=": float.__ge__, ">": float.__gt__, "<=": float.__le__, "<": float.__lt__}


def _check_text(name: str, check: str) -> str:
    lo, hi = _parse_check(check)
    if lo and hi:
        flip = {">=": "<=", ">": "<"}
        return f"{_num(lo[1])} {flip[lo[0]]} {name} {hi[0]} {_num(hi[1])}"
    op, value = lo or hi  # type: ignore[misc]
    return f"{name} {op} {_num(value)}"


def _num(x: float) -> str:
    return str(int(x)) if x.is_integer() else repr(x)


def validate(obj: Any, section: str, extra: Mapping[str, bool] | None = None) -> None:
    """Check every field of dataclass ``obj`` declared with :func:`setting` against its range
    or choices (each item of a tuple field; ``None`` passes), and the ``extra`` conditions
    (description → holds); ValueError naming all that fail: ``invalid <section> settings: need …``."""
    bad: list[str] = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        # a list (tuple field) is checked item by item; None (an optional field unset) passes
        items = value if isinstance(value, tuple) else () if value is None else (value,)
        choices = f.metadata.get("choices")
        if choices is not None and any(v not in choices for v in items):
            bad.append(f"{f.name} in ({', '.join(map(str, choices))}), not {value!r}")
        check = f.metadata.get("check")
        if check is not None:
            lo, hi = _parse_check(check)
            ok = all(_OPS[op](float(v), bound) for v in items for op, bound in filter(None, (lo, hi)))
            if not ok:
                bad.append(f"{_check_text(f.name, check)} (got {value!r})")
    bad += [k for k, ok in (extra or {}).items() if not ok]
    if bad:
        raise ValueError(f"invalid {section} settings: need {', '.join(bad)}")
