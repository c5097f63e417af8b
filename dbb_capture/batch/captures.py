"""Which sub-folders of CAPTURES_DIR are captures, what kind each is, and where its outputs go."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..capture.footage import VIDEO_EXTS
from ..capture.object_spec import object_kind
from ..core.errors import DbbError

# A folder holding any of these is meant as a capture (docs/formats.md), so a broken one fails
# loudly instead of being passed over; other folders (notes, renders) are left alone.
CAPTURE_MARKS = ("board.json", "object.json", "camera.json", "frames", "raw")


@dataclass(frozen=True)
class CapturePaths:
    """The outputs of one capture: ``OUT/<capture>/{dataset,run,bundle}``."""

    root: Path

    @property
    def dataset(self) -> Path:
        return self.root / "dataset"

    @property
    def run(self) -> Path:
        return self.root / "run"

    @property
    def bundle(self) -> Path:
        return self.root / "bundle"


@dataclass(frozen=True)
class CaptureJob:
    """One capture of the batch. ``kind`` None with ``problem`` set: it cannot start (e.g. a bad
    ``kind`` in its object.json) and fails alone."""

    name: str
    folder: Path
    kind: str | None
    kind_source: str                 # "object.json" or "default" (the batch's default kind)
    paths: CapturePaths
    problem: str | None = None


def is_capture(folder: Path) -> bool:
    """Whether ``folder`` looks like a capture: footage, a board or an object file inside."""
    if any((folder / m).exists() for m in CAPTURE_MARKS):
        return True
    return any(p.is_file() and (p.suffix.lower() in VIDEO_EXTS or p.suffix.lower() == ".r3d")
               for p in folder.iterdir())


def find_captures(root: Path, out: Path, default_kind: str) -> tuple[list[CaptureJob], list[str]]:
    """The captures among the sub-folders of ``root`` (sorted by name; hidden folders and ``out``
    itself left out) and the names of the sub-folders that are not captures."""
    root, out = Path(root), Path(out)
    if not root.is_dir():
        raise DbbError(f"captures folder not found: {root}")
    jobs, others = [], []
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if folder.resolve() == out.resolve():
            continue
        if not is_capture(folder):
            others.append(folder.name)
            continue
        jobs.append(_job(folder, out / folder.name, default_kind))
    if not jobs:
        raise DbbError(f"no captures in {root}: expected sub-folders each holding footage (video.mp4, frames/, "
                       f"raw/ or a .r3d) and board.json")
    return jobs, others


def _job(folder: Path, out: Path, default_kind: str) -> CaptureJob:
    try:
        kind = object_kind(folder / "object.json")
    except DbbError as e:
        return CaptureJob(folder.name, folder, None, "object.json", CapturePaths(out), problem=str(e))
    if kind is None:
        return CaptureJob(folder.name, folder, default_kind, "default", CapturePaths(out))
    return CaptureJob(folder.name, folder, kind, "object.json", CapturePaths(out))
