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
  run); dynamic — ``stepper.ts`` (TorchScript stepper), ``rssm.pt`` (weights and config) and
  ``first_frame.png`` (the straight RGBA context frame, with its viewpoint in the manifest);
- ``proxy.glb``: the physics proxy (:mod:`dbb_capture.bundle.proxy`) in bundle space;
- ``previews/``: ``turntable.gif``, ``sheet.png`` (straight RGBA, several elevations), and for
  dynamic bundles ``rollout.png``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import tempfile
import zipfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import DbbError
from ..core.outputs import write_json

FORMAT = "deep-billboard"


VERSION = 1


MANIFEST = "manifest.json"


CHECKSUM = "manifest.sha256"


# What readers of each kind look up (besides the fields every manifest has).
_KIND_KEYS = {"static": (("model", "file"),),
              "dynamic": (("model", "file"), ("inputs", "frame_size"), ("inputs", "crop_fill"),
                          ("inputs", "first_frame"), ("inputs", "first_view"), ("previews", "rollout"))}


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
        """Validate the schema; a foreign or broken manifest gives one clear :class:`DbbError`."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            got = d.get("format") if isinstance(d, dict) else type(d).__name__
            raise DbbError(f"{where} is not a deep-billboard manifest (format {got!r})")
        if not isinstance(d.get("version"), int) or d["version"] > VERSION:
            raise DbbError(f"{where}: bundle version {d.get('version')!r} is not supported (this tool reads <= {VERSION})")
        need = [f for f in ("kind", "model", "inputs", "proxy_mesh", "bundle_from_board", "object", "up",
                            "canvas", "previews", "created", "files") if f not in d]
        if need:
            raise DbbError(f"{where}: missing {', '.join(need)}")
        if d["kind"] not in ("static", "dynamic"):
            raise DbbError(f"{where}: kind must be static or dynamic, not {d['kind']!r}")
        need = _KIND_KEYS[d["kind"]] + (("object", "center"), ("object", "radius"), ("proxy_mesh", "file"),
                                        ("previews", "sheet"), ("previews", "cell_px"))
        lacking = [f"{a}.{b}" for a, b in need if not isinstance(d[a], dict) or b not in d[a]]
        if lacking:
            raise DbbError(f"{where}: missing {', '.join(lacking)}")
        try:
            T = np.asarray(d["bundle_from_board"], float)
        except (TypeError, ValueError):
            T = np.zeros(0)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DbbError(f"{where}: bundle_from_board must be a 4x4 matrix")
        try:
            files = [FileEntry(str(e["path"]), str(e["sha256"]), int(e["bytes"])) for e in d["files"]]
        except (TypeError, KeyError, ValueError):
            raise DbbError(f"{where}: files must be [{{path, sha256, bytes}}]") from None
        plane = d.get("support_plane")
        if plane is not None and support_plane_of(plane) is None:
            raise DbbError(f"{where}: support_plane must be {{point: [x, y, z], normal: [x, y, z]}} (unit normal)")
        return cls(d["kind"], d["model"], d["inputs"], d["proxy_mesh"], T.tolist(), d["object"], d["up"],
                   d["canvas"], d.get("colour_activation"), d["previews"], d["created"], files, plane)

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


def _safe_extract(zf: zipfile.ZipFile, dest: Path, where: Path) -> None:
    for name in zf.namelist():
        if name.startswith("/") or ".." in Path(name).parts:
            raise DbbError(f"{where}: zip member {name!r} points outside the bundle")
    try:
        zf.extractall(dest)
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise DbbError(f"{where} is a corrupt bundle zip: {e}") from None


@contextlib.contextmanager
def open_bundle(path: Path) -> Iterator[Bundle]:
    """Open a bundle folder or ``.dbb`` zip (extracted into a scratch folder while open)."""
    path = Path(path)
    if path.is_dir():
        yield Bundle(path, path, _read_manifest(path, path))
        return
    if not path.is_file():
        raise DbbError(f"bundle not found: {path}")
    if not zipfile.is_zipfile(path):
        raise DbbError(f"{path} is neither a bundle folder nor a .dbb zip")
    with tempfile.TemporaryDirectory(prefix="dbb-bundle-") as tmp:
        try:
            with zipfile.ZipFile(path) as zf:
                _safe_extract(zf, Path(tmp), path)
        except zipfile.BadZipFile as e:
            raise DbbError(f"{path} is a corrupt bundle zip: {e}") from None
        yield Bundle(Path(tmp), path, _read_manifest(Path(tmp), path))


def _read_manifest(root: Path, source: Path) -> Manifest:
    if not (root / MANIFEST).is_file():
        raise DbbError(f"{source} is not a deep-billboard bundle (no {MANIFEST} at its root)")
    try:
        d = json.loads((root / MANIFEST).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DbbError(f"{source}: {MANIFEST} is not valid JSON ({e})") from None
    return Manifest.from_json(d, f"{source}/{MANIFEST}")
