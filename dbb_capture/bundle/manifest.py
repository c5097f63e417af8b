"""Billboard asset bundles: what a bundle holds, its manifest, and opening one.

A bundle is a folder (or the same folder zipped, ``.dbb``) holding:

- ``manifest.json``: :class:`Manifest` (format ``"deep-billboard"``, version, kind, model and
  the inputs it expects, ``bundle_from_board``, object sphere and up in the board frame,
  billboard canvas size in metres, colour activation, previews, creation details, the
  support plane in bundle space where the capture measured one (null otherwise; absent in
  bundles written before it was added, which read and verify as before), and
  ``files``: path, sha256 and bytes of every other file);
- ``manifest.sha256``: the sha256 of ``manifest.json`` (``sha256sum -c`` format), so a changed
  byte anywhere in the bundle is caught;
- ``model/``: static — ``plenoctree.npz`` (svox ``N3Tree`` npz, copied byte for byte from the
  run); dynamic — ``stepper.ts`` (TorchScript stepper), ``rssm.pt`` (weights and config), ``anchor.npz``
  (the view anchor's PlenOctree, whose renders the stepper carries) and
  ``first_frame.png`` (the straight RGBA context frame, with its viewpoint in the manifest);
- ``proxy.glb``: the physics proxy (:mod:`dbb_capture.bundle.proxy`) in bundle space;
- ``previews/``: ``turntable.gif``, ``sheet.png`` (straight RGBA, several elevations), and for
  dynamic bundles ``rollout.png``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import DbbError, InputError
from ..core.fields import entry, number, numbers, shown, text, type_name
from ..core.outputs import write_json
from ..core.zips import DAMAGED, ZIP_MAGIC, check_zip_headers, reason

FORMAT = "deep-billboard"


VERSION = 1


MANIFEST = "manifest.json"


CHECKSUM = "manifest.sha256"


MAX_RADIUS_M = 1000.0       # an object sphere wider than this is a damaged number, not a billboard
MAX_PREVIEW_PX = 4096       # previews' cells and model frames are at most this many pixels a side
_SHA256 = re.compile(r"[0-9a-f]{64}")


@dataclass(frozen=True)
class FileEntry:
    path: str                 # relative, forward slashes
    sha256: str
    bytes: int


@dataclass
class Manifest:
    """``manifest.json`` of a bundle."""

    kind: str                                  # "static" or "dynamic"
    model: dict                                # type, file(s), format details
    inputs: dict                               # what the model expects at run time
    proxy_mesh: dict                           # ProxyMesh.to_json
    bundle_from_board: list[list[float]]       # 4x4
    object: dict                               # {center, radius} board frame, metres
    up: list[float]                            # board frame
    canvas: dict                               # {size_m, note}
    colour_activation: str | None
    previews: dict
    created: dict
    files: list[FileEntry] = field(default_factory=list)
    support_plane: dict | None = None          # {point, normal, note}: bundle space, metres (the table)
    format: str = FORMAT
    version: int = VERSION

    def to_json(self) -> dict:
        d = asdict(self)
        files = d.pop("files")                 # the long list last
        return {"format": d.pop("format"), "version": d.pop("version"), **d, "files": files}

    @classmethod
    def from_json(cls, d: object, where: str = MANIFEST) -> Manifest:
        """Validate every entry a reader relies on, once; a foreign or broken manifest gives one
        clear :class:`DbbError` naming the entry and what it must be."""
        fmt = entry(d, "format", where, None)
        if fmt != FORMAT:
            raise InputError(f"{where} is not a deep-billboard manifest (format {shown(fmt)})")
        raw = entry(d, "version", where)
        version = number(raw, "version", where, low=0, integer=True)
        if version > VERSION:
            raise InputError(f"{where}: bundle version {shown(raw)} is not supported (this tool reads <= {VERSION})")
        kind = text(entry(d, "kind", where), "kind", where)
        if kind not in ("static", "dynamic"):
            raise InputError(f"{where}: kind must be static or dynamic, not {shown(kind)}")
        model, inputs, proxy, obj, canvas, previews = (
            _object(d, k, where) for k in ("model", "inputs", "proxy_mesh", "object", "canvas", "previews"))
        named = [_file(model, "model", where), _file(proxy, "proxy_mesh", where)]
        T = _rigid(entry(d, "bundle_from_board", where), "bundle_from_board", where)
        numbers(entry(obj, "center", f"{where}: object"), "object.center", where, (3,))
        number(entry(obj, "radius", f"{where}: object"), "object.radius", where, low=0, low_open=True,
               high=MAX_RADIUS_M, unit=" m")
        _unit(entry(d, "up", where), "up", where)
        number(entry(canvas, "size_m", f"{where}: canvas"), "canvas.size_m", where, low=0, low_open=True,
               unit=" m")
        act = entry(d, "colour_activation", where, None)
        if act is not None:
            text(act, "colour_activation", where)
        number(entry(previews, "cell_px", f"{where}: previews"), "previews.cell_px", where, low=1,
               high=MAX_PREVIEW_PX, integer=True)
        named.append(_views_file(previews, "sheet", where))
        if kind == "dynamic":
            number(entry(inputs, "frame_size", f"{where}: inputs"), "inputs.frame_size", where, low=1,
                   high=MAX_PREVIEW_PX, integer=True)
            number(entry(inputs, "crop_fill", f"{where}: inputs"), "inputs.crop_fill", where, low=0,
                   low_open=True, high=1)
            numbers(entry(inputs, "first_view", f"{where}: inputs"), "inputs.first_view", where, (3,))
            named.append(text(entry(inputs, "first_frame", f"{where}: inputs"), "inputs.first_frame", where))
            named.append(_rollout(previews, where))
        _object(d, "created", where)
        files = _files(entry(d, "files", where), where)
        unlisted = sorted(set(named) - {e.path for e in files})
        if unlisted:
            raise InputError(f"{where}: files does not list {', '.join(unlisted[:3])}, which the manifest names")
        plane = d.get("support_plane")
        if plane is not None and support_plane_of(plane) is None:
            raise InputError(f"{where}: support_plane must be {{point: [x, y, z], normal: [x, y, z]}} (unit normal)")
        return cls(kind, model, inputs, proxy, T.tolist(), obj, d["up"], canvas, act, previews, d["created"],
                   files, plane, version=version)

    @property
    def T(self) -> np.ndarray:
        return np.asarray(self.bundle_from_board, float)

    @property
    def center(self) -> np.ndarray:
        return np.asarray(self.object["center"], float)

    @property
    def radius(self) -> float:
        return float(self.object["radius"])

    @property
    def support(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The support plane in bundle space: (point (3,), unit normal (3,)), or None."""
        return None if self.support_plane is None else support_plane_of(self.support_plane)


def _object(d: dict, key: str, where: str) -> dict:
    """``d[key]``, which must be a JSON object."""
    v = entry(d, key, where)
    if not isinstance(v, dict):
        raise InputError(f"{where}: {key} must be an object, not {type_name(v)} ({shown(v)})")
    return v


def _file(d: dict, name: str, where: str) -> str:
    """``d["file"]``: a bundle-relative path (``name`` is the entry holding ``d``)."""
    return text(entry(d, "file", f"{where}: {name}"), f"{name}.file", where)


def _rigid(value: object, name: str, where: str) -> np.ndarray:
    """``value`` as a rigid 4x4 transform (rotation and translation; last row 0 0 0 1)."""
    if not isinstance(value, list) or len(value) != 4:
        raise InputError(f"{where}: {name} must be a 4x4 list of numbers, not {type_name(value)} ({shown(value)})")
    T = np.array([numbers(row, f"{name}[{i}]", where, (4,)) for i, row in enumerate(value)])
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) \
            or np.linalg.det(R) < 0:
        raise InputError(f"{where}: {name} must be a rigid transform (a rotation, a translation, last row 0 0 0 1)")
    return T


def _unit(value: object, name: str, where: str) -> list[float]:
    """``value`` as a unit 3-vector."""
    v = numbers(value, name, where, (3,))
    if abs(float(np.linalg.norm(v)) - 1.0) > 1e-3:
        raise InputError(f"{where}: {name} must be a unit vector, not {shown(v)}")
    return v


def _views(value: object, name: str, where: str) -> None:
    """``value`` as a non-empty list of [azimuth_deg, elevation_deg, distance_m] views."""
    if not isinstance(value, list) or not value:
        raise InputError(f"{where}: {name} must be a list of [azimuth_deg, elevation_deg, distance_m], "
                         f"not {type_name(value)} ({shown(value)})")
    for i, v in enumerate(value):
        distance = numbers(v, f"{name}[{i}]", where, (3,))[2]
        number(distance, f"{name}[{i}] distance", where, low=0, low_open=True, unit=" m")


def _views_file(previews: dict, key: str, where: str) -> str:
    """Checks ``previews[key]`` (a tiled preview image: file, columns, views); returns its file."""
    p = _object(previews, key, f"{where}: previews")
    number(entry(p, "columns", f"{where}: previews.{key}"), f"previews.{key}.columns", where, low=1, integer=True)
    _views(entry(p, "views", f"{where}: previews.{key}"), f"previews.{key}.views", where)
    return _file(p, f"previews.{key}", where)


def _rollout(previews: dict, where: str) -> str:
    """Checks ``previews.rollout`` (file, columns, seed, rows.still) of a dynamic bundle; returns its file."""
    p = _object(previews, "rollout", f"{where}: previews")
    number(entry(p, "columns", f"{where}: previews.rollout"), "previews.rollout.columns", where, low=1, integer=True)
    number(entry(p, "seed", f"{where}: previews.rollout"), "previews.rollout.seed", where, low=0, integer=True)
    rows = _object(p, "rows", f"{where}: previews.rollout")
    _views(entry(rows, "still", f"{where}: previews.rollout.rows"), "previews.rollout.rows.still", where)
    return _file(p, "previews.rollout", where)


def _files(value: object, where: str) -> list[FileEntry]:
    """The ``files`` list: {path, sha256, bytes} of every file but the manifest and its checksum."""
    if not isinstance(value, list):
        raise InputError(f"{where}: files must be a list of {{path, sha256, bytes}}, not {type_name(value)}")
    out = []
    for i, e in enumerate(value):
        name = f"files[{i}]"
        path = text(entry(e, "path", f"{where}: {name}"), f"{name}.path", where)
        digest = text(entry(e, "sha256", f"{where}: {name}"), f"{name}.sha256", where)
        if not _SHA256.fullmatch(digest):
            raise InputError(f"{where}: {name}.sha256 must be 64 hex digits, not {shown(digest)}")
        size = number(entry(e, "bytes", f"{where}: {name}"), f"{name}.bytes", where, low=0, integer=True)
        out.append(FileEntry(path, digest, int(size)))
    return out


def support_plane_of(d: object) -> tuple[np.ndarray, np.ndarray] | None:
    """(point (3,), normal (3,)) of a manifest's ``support_plane`` entry, None if malformed."""
    try:
        p, n = np.asarray(d["point"], float), np.asarray(d["normal"], float)      # type: ignore[index]
    except (TypeError, KeyError, ValueError, IndexError):
        return None
    ok = p.shape == n.shape == (3,) and np.all(np.isfinite(p)) and np.all(np.isfinite(n))
    return (p, n) if ok and abs(float(np.linalg.norm(n)) - 1.0) < 1e-3 else None


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_entries(root: Path) -> list[FileEntry]:
    """Every file under ``root`` but the manifest and its checksum, sorted by path."""
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and rel not in (MANIFEST, CHECKSUM):
            out.append(FileEntry(rel, sha256_of(p), p.stat().st_size))
    return out


def write_manifest(root: Path, m: Manifest) -> None:
    """Fill ``m.files`` from ``root``, write ``manifest.json`` and its checksum."""
    m.files = file_entries(root)
    write_json(root / MANIFEST, m.to_json())
    (root / CHECKSUM).write_text(f"{sha256_of(root / MANIFEST)}  {MANIFEST}\n")


@dataclass
class Bundle:
    """An opened bundle: its folder (a zip is extracted to a scratch folder) and manifest."""

    root: Path
    source: Path
    manifest: Manifest

    def file(self, rel: str) -> Path:
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root.resolve()):
            raise DbbError(f"{self.source}: file {rel!r} points outside the bundle")
        if not p.is_file():
            raise DbbError(f"{self.source}: {rel} is missing")
        return p


def _extract(path: Path, dest: Path) -> None:
    """Unpack the ``.dbb`` zip ``path`` into ``dest``: every member's name inside the bundle,
    its header consistent and its bytes matching their CRC, or one clear error."""
    with open(path, "rb") as f:
        head = f.read(4)
    if head not in ZIP_MAGIC:
        raise DbbError(f"{path} is neither a bundle folder nor a .dbb zip")
    try:
        with zipfile.ZipFile(path) as zf:
            check_zip_headers(zf, f"bundle zip {path}")
            for name in zf.namelist():
                if name.startswith("/") or ".." in Path(name).parts:
                    raise DbbError(f"{path}: zip member {name!r} points outside the bundle")
            zf.extractall(dest)
    except DbbError:
        raise
    except DAMAGED as e:
        raise DbbError(f"bundle zip {path} is damaged ({reason(e)})") from None


@contextlib.contextmanager
def open_bundle(path: Path) -> Iterator[Bundle]:
    """Open a bundle folder or ``.dbb`` zip (extracted into a scratch folder while open)."""
    path = Path(path)
    if path.is_dir():
        yield Bundle(path, path, _read_manifest(path, path))
        return
    if not path.is_file():
        raise DbbError(f"bundle not found: {path}")
    with tempfile.TemporaryDirectory(prefix="dbb-bundle-") as tmp:
        _extract(path, Path(tmp))
        yield Bundle(Path(tmp), path, _read_manifest(Path(tmp), path))


def _read_manifest(root: Path, source: Path) -> Manifest:
    if not (root / MANIFEST).is_file():
        raise DbbError(f"{source} is not a deep-billboard bundle (no {MANIFEST} at its root)")
    try:
        d = json.loads((root / MANIFEST).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DbbError(f"{source}: {MANIFEST} is not valid JSON ({e})") from None
    return Manifest.from_json(d, f"{source}/{MANIFEST}")
