"""Typed reads of a trainer's checkpoint (the dict ``torch.save`` wrote), each failure one clear
:class:`InputError` line naming the checkpoint, the entry and what it must be.

A resumed run reads its checkpoint before any work; a damaged or foreign one is refused there,
whole, instead of failing mid-training, at the bake, or training on from NaN weights.
Entries are named as dotted paths into the checkpoint (``field.density``, ``model.gru.weight``).
"""

from __future__ import annotations

import dataclasses
import math
import pickle
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from .errors import DbbError, InputError
from .fields import MISSING, number, shown, type_name

T = typing.TypeVar("T")


def load(path: Path, what: str) -> dict:
    """The dict saved at ``path`` (``what``: e.g. "RSSM checkpoint"), on the CPU.

    Read as data only (tensors, numbers, strings, lists, dicts): a damaged pickle cannot call
    anything while it is read, and every way it fails is one line."""
    try:
        st = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:          # a damaged file fails in many ways inside the unpickler
        first = (str(e).strip().splitlines() or [""])[0].split(". ")[0].rstrip(".")
        if isinstance(e, pickle.UnpicklingError) and first.startswith("Weights only load failed"):
            first = "it holds more than tensors and plain values"
        detail = f"{type(e).__name__}: {first}" if first else type(e).__name__
        raise InputError(f"cannot read {what} {path} (damaged, or not a checkpoint): {detail}") from None
    if not isinstance(st, dict):
        raise InputError(f"{path}: not a {what} (it holds {type_name(st)}, not a dict of entries)")
    return st


def part(doc: Any, name: str, where: str, default: Any = MISSING) -> Any:
    """The entry ``name`` (dotted: its last key is read from ``doc``, the rest names ``doc``)."""
    parent, _, key = name.rpartition(".")
    if not isinstance(doc, dict):
        raise InputError(f"{where}: {parent or 'the checkpoint'} must be a dict of entries, not {type_name(doc)}")
    value = doc.get(key, default)
    if value is MISSING:
        raise InputError(f"{where}: {name} is missing")
    return value


def dims(shape: Sequence[int]) -> str:
    return "x".join(str(int(n)) for n in shape) or "a scalar"


def tensor(value: Any, name: str, where: str, shape: Sequence[int | None], floating: bool = True) -> torch.Tensor:
    """``value`` as a tensor of ``shape`` (None: any length on that axis) holding floats (finite)
    or, without ``floating``, integers."""
    if not isinstance(value, torch.Tensor):
        raise InputError(f"{where}: {name} must be a tensor, not {type_name(value)} ({shown(value)})")
    if value.ndim != len(shape) or any(s is not None and n != s for n, s in zip(value.shape, shape)):
        want = "x".join("N" if s is None else str(s) for s in shape)
        raise InputError(f"{where}: {name} must be a tensor of shape {want}, not {dims(value.shape)}")
    if floating != value.is_floating_point() or value.is_complex() or value.dtype == torch.bool:
        raise InputError(f"{where}: {name} must hold {'floats' if floating else 'integers'}, not {value.dtype}")
    if floating and not bool(torch.isfinite(value).all()):
        bad = int((~torch.isfinite(value)).sum())
        raise InputError(f"{where}: {name} must hold finite numbers, and {bad} of its {value.numel()} are NaN or infinite")
    return value


def state_dict(value: Any, like: Mapping[str, torch.Tensor], name: str, where: str) -> dict[str, torch.Tensor]:
    """``value`` as a state dict of exactly the tensors of ``like`` (a module's own), each of its
    shape and kind, floats finite."""
    if not isinstance(value, dict):
        raise InputError(f"{where}: {name} must be a dict of tensors, not {type_name(value)} ({shown(value)})")
    missing, extra = [k for k in like if k not in value], [k for k in value if k not in like]
    if missing or extra:
        say = ([f"lacks {', '.join(map(str, missing[:3]))}"] if missing else []) + \
              ([f"has unknown {', '.join(map(str, extra[:3]))}"] if extra else [])
        raise InputError(f"{where}: {name} {' and '.join(say)} (not this model's weights)")
    return {k: tensor(value[k], f"{name}.{k}", where, tuple(t.shape), t.is_floating_point()) for k, t in like.items()}


def progress(st: dict, where: str) -> tuple[int, float]:
    """The checkpoint's ``step`` (a whole number >= 0) and ``seconds`` of training (finite, >= 0)."""
    step = number(part(st, "step", where), "step", where, low=0, integer=True)
    seconds = number(part(st, "seconds", where), "seconds", where, low=0)
    return int(step), seconds


def history(value: Any, name: str, where: str) -> list[dict]:
    """``value`` as a list of dicts of numbers (a training history: step, seconds, losses ...)."""
    if not isinstance(value, list):
        raise InputError(f"{where}: {name} must be a list, not {type_name(value)} ({shown(value)})")
    for i, row in enumerate(value):
        if not isinstance(row, dict):
            raise InputError(f"{where}: {name}[{i}] must be a dict of numbers, not {type_name(row)} ({shown(row)})")
        for k, v in row.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise InputError(f"{where}: {name}[{i}].{k} must be a number, not {type_name(v)} ({shown(v)})")
    return value


def config(value: Any, cls: type[T], name: str, where: str) -> T:
    """``value`` (what :func:`dataclasses.asdict` wrote) as the dataclass ``cls``: only its
    settings, each of the type it declares (settings absent take their defaults), then its own
    ``validate()`` if it has one."""
    if not isinstance(value, dict):
        raise InputError(f"{where}: {name} must be a dict of settings, not {type_name(value)} ({shown(value)})")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = [str(k) for k in value if k not in known]
    if unknown:
        raise InputError(f"{where}: {name} has settings this version does not know: {', '.join(unknown[:4])}")
    for k, v in value.items():
        if not _fits(v, hints[k]):
            raise InputError(f"{where}: {name}.{k} must be {_words(hints[k])}, not {type_name(v)} ({shown(v)})")
    out = cls(**value)
    try:
        getattr(out, "validate", lambda: None)()
    except DbbError as e:
        raise InputError(f"{where}: {name} is not valid: {e}") from None
    return out


def _fits(value: Any, hint: Any) -> bool:
    """Whether ``value`` is of the declared type ``hint`` (the plain types settings use)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if hint is str:
        return isinstance(value, str)
    if origin is tuple or hint is tuple:
        return isinstance(value, (tuple, list)) and all(_fits(v, args[0] if args else Any) for v in value)
    if origin is dict or hint is dict:
        return isinstance(value, dict) and (len(args) < 2 or all(_fits(v, args[1]) for v in value.values()))
    return True         # a type settings do not use: left to the config's own validate()


def _words(hint: Any) -> str:
    """A declared type in words: "a number", "a whole number or null" ..."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_words(a) for a in args)
    if origin is tuple or hint is tuple:
        return "a list of numbers"
    if origin is dict or hint is dict:
        return "a dict of numbers"
    return {type(None): "null", bool: "true/false", int: "a whole number", float: "a finite number",
            str: "a string"}.get(hint, getattr(hint, "__name__", str(hint)))
