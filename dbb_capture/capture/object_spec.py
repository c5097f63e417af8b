"""The optional ``kind`` of a capture's ``object.json`` (``"static"`` or ``"dynamic"``).

Only ``dbb-batch`` reads it, to choose the trainer; preprocessing reads the sphere
(``center``, ``radius``) and ignores every other entry, so a capture with or without ``kind``
preprocesses the same.
"""

from __future__ import annotations

from pathlib import Path

from ..core.errors import InputError
from ..core.outputs import read_json

OBJECT_KINDS = ("static", "dynamic")


def object_kind(path: Path) -> str | None:
    """The ``kind`` entry of the ``object.json`` at ``path``: ``"static"``, ``"dynamic"``, or None
    where the file or the entry is absent; an :class:`InputError` for any other value."""
    path = Path(path)
    if not path.is_file():
        return None
    doc = read_json(path, "object file")
    if not isinstance(doc, dict):
        raise InputError(f'{path} must be a JSON object ({{"center": [x, y, z], "radius": r, "kind": ...}})')
    kind = doc.get("kind")
    if kind is None:
        return None
    if kind not in OBJECT_KINDS:
        raise InputError(f"{path}: kind {kind!r} is neither 'static' nor 'dynamic'")
    return str(kind)
