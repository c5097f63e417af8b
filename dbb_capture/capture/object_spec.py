"""A capture's ``object.json``: the sphere that holds the object, and its optional ``kind``.

``{"center": [x, y, z], "radius": r}`` in the board frame (metres), optionally with
``"kind": "static"|"dynamic"`` (only ``dbb-batch`` uses it, to choose the trainer). Other
entries are ignored. Preprocessing checks the file before any work: the sphere must be a
real one and lie near the board (:data:`NEAR_BOARD` board diagonals of its centre), since
the cameras that see the board must see the object too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.errors import InputError
from ..core.fields import number, numbers
from ..core.outputs import read_json
from .board import BoardSpec

OBJECT_KINDS = ("static", "dynamic")
HINT = '{"center": [x, y, z], "radius": r}, board frame, metres'
NEAR_BOARD = 5.0        # the sphere must reach within this many board diagonals of the board's centre


def _doc(path: Path) -> dict:
    doc = read_json(path, "object file")
    if not isinstance(doc, dict):
        raise InputError(f"{path} must be a JSON object (expected {HINT})")
    return doc


def object_kind(path: Path) -> str | None:
    """The ``kind`` entry of the ``object.json`` at ``path``: ``"static"``, ``"dynamic"``, or None
    where the file or the entry is absent; an :class:`InputError` for any other value."""
    path = Path(path)
    if not path.is_file():
        return None
    return _kind(_doc(path), path)


def _kind(doc: dict, path: Path) -> str | None:
    kind = doc.get("kind")
    if kind is None:
        return None
    if kind not in OBJECT_KINDS:
        raise InputError(f"{path}: kind {kind!r} is neither 'static' nor 'dynamic'")
    return str(kind)


def load_object_sphere(path: Path, board: BoardSpec | None = None) -> tuple[np.ndarray, float]:
    """The sphere of the ``object.json`` at ``path``: centre (3,) and radius, board frame,
    metres; its ``kind`` checked too. With ``board``, a sphere far from the board (a centre in
    other units or another frame) is refused before the poses are solved."""
    path = Path(path)
    doc = _doc(path)
    missing = [k for k in ("center", "radius") if k not in doc]
    if missing:
        raise InputError(f"{path}: {' and '.join(missing)} missing (expected {HINT})")
    center = np.array(numbers(doc["center"], "center", str(path), (3,), hint=f" (expected {HINT})"))
    radius = number(doc["radius"], "radius", str(path), low=0, low_open=True, unit=" m")
    _kind(doc, path)
    if board is not None:
        reach = NEAR_BOARD * float(np.hypot(*board.size_m))
        away = float(np.linalg.norm(center - board.center))
        if away - radius > reach or radius > reach:
            raise InputError(
                f"{path}: the object's sphere (centre {np.round(center, 3).tolist()}, radius {radius:g} m) is "
                f"{'too large' if radius > reach else f'{away:.2f} m from the board centre'}: it must lie within "
                f"{reach:.2f} m of it ({NEAR_BOARD:g} board diagonals; board frame, metres, origin at the "
                f"board's top-left corner)")
    return center, radius
