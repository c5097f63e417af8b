"""Typed reads of entries of a JSON document, each failure one clear :class:`InputError` line
naming the file, the entry and what it must be.

JSON has one number type and no NaN: a number must be an int or a float (never a bool, never
a string of digits), finite, and in the range the entry allows; an integer may be written
``7`` or ``7.0``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

from .errors import InputError

MISSING = object()


def shown(value: Any) -> str:
    """A value as it reads in the file, shortened to one line (``NaN`` and ``Infinity`` as JSON writes them)."""
    try:
        text = json.dumps(value, allow_nan=True)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def entry(doc: Any, key: str, where: str, default: Any = MISSING, parent: str = "") -> Any:
    """``doc[key]`` of the JSON object ``doc``; ``default`` where it is absent (or an error
    naming the entry when no default is given). ``parent`` names ``doc`` inside the file
    (``frames[0]``), so messages say ``frames[0].file_path``."""
    if not isinstance(doc, dict):
        what = f"{parent} must be" if parent else "expected"
        raise InputError(f"{where}: {what} a JSON object, not {type_name(doc)} ({shown(doc)})")
    if key in doc:
        return doc[key]
    if default is MISSING:
        raise InputError(f"{where}: {parent + '.' if parent else ''}{key} is missing")
    return default


def type_name(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "true/false", type(None): "null"}.get(
        type(value), "a number" if isinstance(value, (int, float)) else type(value).__name__)


def number(value: Any, name: str, where: str, *, low: float | None = None, high: float | None = None,
           low_open: bool = False, integer: bool = False, unit: str = "") -> float:
    """``value`` as a finite number in [``low``, ``high``] (``low`` excluded with ``low_open``);
    with ``integer`` a whole number (returned as an int)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: {name} must be a number, not {type_name(value)} ({shown(value)})")
    if not math.isfinite(value):
        raise InputError(f"{where}: {name} must be a finite number, not {shown(value)}")
    bad = (low is not None and (value <= low if low_open else value < low)) or (high is not None and value > high)
    if bad:         # before the whole-number test: 1e30 is out of range more than it is not whole
        lo = "" if low is None else (f"above {low:g}" if low_open else f"at least {low:g}")
        hi = "" if high is None else f"at most {high:g}"
        rule = " and ".join(p for p in (lo, hi) if p)
        raise InputError(f"{where}: {name} {shown(value)}{unit} must be {rule}{unit}")
    if integer and float(value) != int(value):
        raise InputError(f"{where}: {name} must be a whole number, not {shown(value)}")
    return int(value) if integer else float(value)


def numbers(value: Any, name: str, where: str, lengths: Sequence[int], hint: str = "") -> list[float]:
    """``value`` as a list of finite numbers whose length is one of ``lengths``."""
    what = (f"at most {lengths[-1]}" if isinstance(lengths, range) and lengths.start == 0
            else " or ".join(str(n) for n in lengths))
    if not isinstance(value, list) or len(value) not in lengths:
        got = f"{len(value)} values" if isinstance(value, list) else f"{type_name(value)} ({shown(value)})"
        raise InputError(f"{where}: {name} must be a list of {what} numbers{hint}, not {got}")
    return [number(v, f"{name}[{i}]", where) for i, v in enumerate(value)]


def flag(value: Any, name: str, where: str) -> bool:
    """``value`` as JSON's true or false."""
    if not isinstance(value, bool):
        raise InputError(f"{where}: {name} must be true or false, not {shown(value)}")
    return value


def text(value: Any, name: str, where: str) -> str:
    """``value`` as a string."""
    if not isinstance(value, str):
        raise InputError(f"{where}: {name} must be a string, not {type_name(value)} ({shown(value)})")
    return value


def matrix(value: Any, name: str, where: str, shapes: Sequence[tuple[int, int]] = ((4, 4),)) -> list[list[float]]:
    """``value`` as a list of rows of finite numbers, (rows, columns) one of ``shapes``."""
    want = " or ".join(f"{r}x{c}" for r, c in shapes)
    if not isinstance(value, list) or not all(isinstance(r, list) for r in value):
        got = (f"a flat list of {len(value)} values" if isinstance(value, list)
               else f"{type_name(value)} ({shown(value)})")
    elif len({len(r) for r in value}) > 1:
        got = "rows of " + " and ".join(str(n) for n in sorted({len(r) for r in value})) + " values"
    elif (len(value), len(value[0]) if value else 0) not in shapes:
        got = f"{len(value)}x{len(value[0]) if value else 0}"
    else:
        return [[number(v, f"{name}[{i}][{j}]", where) for j, v in enumerate(r)] for i, r in enumerate(value)]
    raise InputError(f"{where}: {name} must be a {want} list of numbers, not {got}")

