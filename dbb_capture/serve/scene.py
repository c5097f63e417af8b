"""What a server shows: bundles placed in one world (``scene.json``, or bundles in a row).

``scene.json``::

    {"objects": [{"bundle": "toy.dbb", "position": [0, 0, 0], "yaw_deg": 0, "scale": 1,
                  "id": "toy"}, ...]}

``bundle`` is a folder or ``.dbb`` zip, relative to the scene file; ``position`` (metres) is where
the bundle's origin (the object's centre) goes in the scene frame (+Y up, metres, glTF axes);
``yaw_deg`` turns the bundle about +Y (counter-clockwise seen from above), ``scale`` scales it.
Only ``bundle`` is required; ``id`` defaults to the bundle's file name without extension.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import DbbError

ROW_GAP_M = 0.1             # bundles given without a scene: side by side along +X, this far apart
_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


@dataclass(frozen=True)
class Placement:
    """One object of a scene: its bundle and where bundle space sits in the scene frame."""

    id: str
    bundle: Path
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    scale: float = 1.0

    @property
    def scene_from_bundle(self) -> np.ndarray:
        """4x4: translate(position) @ rotate_y(yaw) @ scale."""
        a = math.radians(self.yaw_deg)
        T = np.eye(4)
        T[:3, :3] = self.scale * np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        T[:3, 3] = self.position
        return T


def is_scene_file(path: Path) -> bool:
    return Path(path).suffix.lower() == ".json" and Path(path).is_file()


def load_scene(path: Path) -> list[Placement]:
    """The placements of a ``scene.json`` (validated; bundle paths resolved against its folder)."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise DbbError(f"cannot read scene file {path}: {e}") from None
    if not isinstance(d, dict) or not isinstance(d.get("objects"), list) or not d["objects"]:
        raise DbbError(f"{path}: a scene file holds {{\"objects\": [{{\"bundle\": ...}}, ...]}} with at least one object")
    out, explicit = [], []
    for i, o in enumerate(d["objects"]):
        where = f"{path} object {i}"
        if not isinstance(o, dict) or not isinstance(o.get("bundle"), str):
            raise DbbError(f"{where}: needs \"bundle\": a bundle folder or .dbb path")
        unknown = set(o) - {"bundle", "position", "yaw_deg", "scale", "id"}
        if unknown:
            raise DbbError(f"{where}: unknown field {sorted(unknown)[0]!r} (bundle, position, yaw_deg, scale, id)")
        pos = o.get("position", [0, 0, 0])
        if (not isinstance(pos, list) or len(pos) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in pos)):
            raise DbbError(f"{where}: position must be [x, y, z] in metres")
        yaw, scale = o.get("yaw_deg", 0.0), o.get("scale", 1.0)
        for name, v in (("yaw_deg", yaw), ("scale", scale)):
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                raise DbbError(f"{where}: {name} must be a number")
        if scale <= 0:
            raise DbbError(f"{where}: scale must be positive")
        bundle = Path(o["bundle"])
        bundle = bundle if bundle.is_absolute() else path.parent / bundle
        pid = o.get("id", _default_id(bundle))
        if not isinstance(pid, str) or not _ID.match(pid):
            raise DbbError(f"{where}: id must be 1-64 letters, digits, '_', '-' or '.'")
        out.append(Placement(pid, bundle, tuple(float(v) for v in pos), float(yaw), float(scale)))
        explicit.append("id" in o)
    return _unique(out, explicit, path)


def row_of(bundles: list[Path], sizes_m: list[float]) -> list[Placement]:
    """Bundles given on the command line: side by side along +X, centred on the origin."""
    xs, x = [], 0.0
    for s in sizes_m:
        xs.append(x + s / 2)
        x += s + ROW_GAP_M
    shift = (x - ROW_GAP_M) / 2
    out = [Placement(_default_id(b), Path(b), (xc - shift, 0.0, 0.0)) for b, xc in zip(bundles, xs, strict=True)]
    return _unique(out, [False] * len(out), None)


def _default_id(bundle: Path) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(bundle).name.removesuffix(".dbb")) or "object"
    return name[:64]


def _unique(objs: list[Placement], explicit: list[bool], where: Path | None) -> list[Placement]:
    """Placements with distinct ids: repeated default ids get ``-2``, ``-3``; a repeated explicit id is refused."""
    seen: dict[str, int] = {}
    out = []
    for o, given in zip(objs, explicit, strict=True):
        if o.id in seen:
            if given:
                raise DbbError(f"{where}: two objects have the id {o.id!r}")
            seen[o.id] += 1
            o = Placement(f"{o.id}-{seen[o.id]}"[:64], o.bundle, o.position, o.yaw_deg, o.scale)
        seen.setdefault(o.id, 1)
        out.append(o)
    return out
