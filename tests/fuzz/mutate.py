"""Seeded corruptions of the toolkit's input files, for the fuzz suite.

A :class:`Case` changes one file in place. Byte cases (any file): truncations at several
points, flipped bytes in the head, the middle and the tail, random bytes, an empty file. JSON
cases (a document): each named entry missing, of a wrong type, NaN, infinite, huge, negative,
zero or of a wrong shape, an extra entry, the document itself of a wrong type. The same seed
always gives the same cases, so a failing case id reproduces.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

TRUNCATE_AT = (0.0, 0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99)     # share of the bytes kept
HEAD_BYTES = 64                                               # "head": where formats keep their headers


@dataclass(frozen=True)
class Case:
    """One corruption: ``id`` names it (and its seed); ``apply(path)`` rewrites the file."""

    id: str
    apply: Callable[[Path], None]
    may_pass: bool = False          # going on is right (a documented warning and success)


def _rewrite(fn: Callable[[bytes], bytes]) -> Callable[[Path], None]:
    def apply(path: Path) -> None:
        path.write_bytes(fn(path.read_bytes()))
    return apply


def _flip(seed: int, n: int, where: str) -> Callable[[bytes], bytes]:
    def fn(data: bytes) -> bytes:
        rng = np.random.default_rng(seed)
        b = bytearray(data)
        lo, hi = {"head": (0, min(HEAD_BYTES, len(b))), "middle": (len(b) // 3, 2 * len(b) // 3),
                  "tail": (max(0, len(b) - HEAD_BYTES), len(b)), "any": (0, len(b))}[where]
        for pos in rng.integers(lo, max(hi, lo + 1), n):
            if pos < len(b):
                b[pos] ^= int(rng.integers(1, 256))
        return bytes(b)
    return fn


def byte_cases(seed: int, truncate_at: Sequence[float] = TRUNCATE_AT,
               flips: Sequence[tuple[int, str]] = ((1, "head"), (4, "head"), (1, "middle"), (16, "middle"),
                                                   (4, "tail"), (64, "any")),
               may_pass: Callable[[str], bool] = lambda cid: False) -> list[Case]:
    """Truncations (``truncate_at``: shares kept), flips (``(n bytes, region)``), random bytes and
    an empty file; ``may_pass(id)`` marks the cases where going on is right."""
    cases = [Case(f"truncate-{int(round(100 * f))}pct", _rewrite(lambda d, f=f: d[:int(len(d) * f)]))
             for f in truncate_at]
    cases += [Case(f"flip-{n}-{where}-s{seed + i}", _rewrite(_flip(seed + i, n, where)))
              for i, (n, where) in enumerate(flips)]
    cases.append(Case(f"random-bytes-s{seed}", _rewrite(
        lambda d: np.random.default_rng(seed).integers(0, 256, len(d), dtype=np.uint8).tobytes())))
    cases.append(Case("empty", _rewrite(lambda d: b"")))
    return [Case(c.id, c.apply, may_pass(c.id)) for c in cases]


# Values that are wrong for any number, and for any list of numbers.
WRONG_TYPES: dict[str, Any] = {"string": "12", "list": [1], "object": {"a": 1}, "null": None, "bool": True}
BAD_NUMBERS: dict[str, Any] = {"nan": float("nan"), "inf": float("inf"), "-inf": float("-inf"),
                               "huge": 1e308, "hugeint": 10 ** 30, "negative": -1.0, "zero": 0}


def _edit(where: Sequence[Any], value: Any = None, delete: bool = False, whole: bool = False
          ) -> Callable[[Path], None]:
    """A case that reads the JSON file, sets (or deletes) the entry at ``where`` (a key path;
    the whole document with ``whole``) and writes it back, NaN and infinities as Python writes them."""
    def apply(path: Path) -> None:
        doc = value if whole else json.loads(path.read_text())
        if not whole:
            node = doc
            for k in where[:-1]:
                node = node[k]
            if delete:
                del node[where[-1]]
            else:
                node[where[-1]] = copy.deepcopy(value)
        path.write_text(json.dumps(doc, allow_nan=True, indent=1))
    return apply


def _name(where: Sequence[Any]) -> str:
    return ".".join(str(k) for k in where)


def json_cases(numbers: Sequence[Sequence[Any]] = (), arrays: Sequence[tuple[Sequence[Any], int]] = (),
               others: Sequence[Sequence[Any]] = (), skip: Callable[[str], bool] = lambda cid: False,
               may_pass: Callable[[str], bool] = lambda cid: False) -> list[Case]:
    """Cases of a JSON document. ``numbers``: paths (key sequences) of numeric entries, each
    missing, of each wrong type and each bad number; ``arrays``: (path, length) of numeric lists,
    each missing, too short, too long, nested, holding a NaN or a string, a number instead;
    ``others``: paths of any other entry, each missing, a number, an empty list, null. Plus an
    extra entry at the top and the whole document replaced by other JSON types. ``skip(id)``
    leaves cases out (values that are right for that entry); ``may_pass(id)``: going on is right."""
    cases: list[Case] = []
    for where in numbers:
        cases.append(Case(f"missing-{_name(where)}", _edit(where, delete=True)))
        for label, v in {**WRONG_TYPES, **BAD_NUMBERS}.items():
            cases.append(Case(f"{label}-{_name(where)}", _edit(where, v)))
    for where, n in arrays:
        cases.append(Case(f"missing-{_name(where)}", _edit(where, delete=True)))
        for label, v in {"short": [0.1] * (n - 1), "long": [0.1] * (n + 1), "nested": [[0.1] * n] * 2,
                         "nan-in": [float("nan")] + [0.1] * (n - 1), "string-in": ["x"] + [0.1] * (n - 1),
                         "number": 0.5}.items():
            cases.append(Case(f"{label}-{_name(where)}", _edit(where, v)))
    for where in others:
        cases.append(Case(f"missing-{_name(where)}", _edit(where, delete=True)))
        for label, v in {"number": 7, "list": [], "null": None}.items():
            cases.append(Case(f"{label}-{_name(where)}", _edit(where, v)))
    cases.append(Case("extra-key", _edit(("zz_extra",), {"unknown": [1, 2]})))
    for label, v in {"list": [1, 2], "string": "x", "number": 3, "null": None}.items():
        cases.append(Case(f"document-{label}", _edit((), v, whole=True)))
    return [Case(c.id, c.apply, may_pass(c.id)) for c in cases if not skip(c.id)]
