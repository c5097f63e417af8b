"""What a preprocess run starts from: the capture's parts, the options, and what every stage sees."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..background.config import BackgroundConfig
from ..capture.board import BoardSpec
from ..capture.footage import FootageSource, R3dSource, capture_footage, open_footage
from ..capture.object_spec import load_object_sphere, object_kind
from ..core.errors import DbbError, InputError
from ..crops.camera import crop_size_for
from ..crops.matte import MatteConfig
from ..geometry.cameras import Intrinsics
from ..poses.detect import DetectorConfig
from ..poses.solve import PoseConfig


@dataclass(frozen=True)
class CaptureInputs:
    """Where a capture's parts are. ``camera`` is None when intrinsics must be calibrated."""

    root: Path
    footage: FootageSource
    board: BoardSpec | None          # None only in fixed-camera mode (no board needed)
    camera: Intrinsics | None
    camera_source: str
    object_json: Path | None
    background: Path | None
    kind: str | None = None          # object.json's "kind" ("static", "dynamic"), None if not given


DYNAMIC_CROP_SIZE = 64    # the RSSM's default image size (dynamic.config), which dynamic crops keep
R3D_INTRINSICS = "Record3D metadata"     # CaptureInputs.camera_source of a Record3D export's own intrinsics


def resolve_capture(capture: Path, board: Path | None = None, camera: Path | None = None,
                    footage: Path | None = None, object_json: Path | None = None,
                    background: Path | None = None, need_board: bool = True) -> CaptureInputs:
    """Find the parts of a capture folder (flags override the files inside it) and check each
    before any work: footage readable, board, camera (its image size the footage's) and object
    sphere (near the board) well formed."""
    capture = Path(capture)
    if not capture.is_dir():
        raise InputError(f"capture folder not found: {capture}")
    src = open_footage(footage) if footage else capture_footage(capture)
    src.info  # probe now: unreadable footage fails before any work starts
    board_spec = None
    if need_board or board is not None or (capture / "board.json").is_file():
        board_spec = BoardSpec.load(board or capture / "board.json")
    cam_path = camera or (capture / "camera.json" if (capture / "camera.json").is_file() else None)
    intr, cam_src = None, "calibrated from the footage"
    if cam_path is not None:
        intr, cam_src = Intrinsics.load(cam_path), str(cam_path)
        if (intr.width, intr.height) != (src.info.width, src.info.height):
            raise InputError(f"{cam_path} is for {intr.width}x{intr.height} images but the footage "
                             f"{src.info.path} is {src.info.width}x{src.info.height}")
    elif isinstance(src, R3dSource):
        intr, cam_src = src.intrinsics(), R3D_INTRINSICS
    obj = object_json or (capture / "object.json" if (capture / "object.json").is_file() else None)
    if obj is not None:
        load_object_sphere(obj, board_spec)
    if background is None:
        for cand in ("background.mp4", "background.mov", "background"):
            if (capture / cand).exists():
                background = capture / cand
                break
    return CaptureInputs(capture, src, board_spec, intr, cam_src, obj, background,
                         object_kind(obj) if obj is not None else None)


@dataclass(frozen=True)
class PreprocessConfig:
    """Options of a run. ``fps``: resample the footage (None: every frame)."""

    fps: float | None = None
    blur_ratio: float = 0.4
    refine: bool = False
    workers: int = 1
    stop_after: str | None = None
    detector: DetectorConfig = DetectorConfig()
    gates: PoseConfig = PoseConfig()
    crop_size: int | None = None          # None: from the footage (:meth:`crop_size_for`)
    max_crop_size: int = 512              # ... at most this
    crop_fill: float = 0.9
    test_fraction: float = 0.2
    sequence_length: int = 11
    use_clean_plate: bool = True          # False: learn the room from the object video even if a plate exists
    crop_window: tuple[int, int, int] | None = None   # fixed camera: crop window (x, y, side) in pixels
    fixed_matte: bool = True              # fixed camera: matte against the background (False: opaque crops)
    background: BackgroundConfig = BackgroundConfig()
    matte: MatteConfig = MatteConfig()

    def validate(self) -> None:
        if self.crop_size is not None and not 16 <= self.crop_size <= 1024:
            raise DbbError(f"{{=crop_size}} {self.crop_size}: expected 16..1024 pixels")
        if not 32 <= self.max_crop_size <= 1024:
            raise DbbError(f"{{=max_crop_size}} {self.max_crop_size}: expected 32..1024 pixels")
        if not 0.2 <= self.crop_fill <= 1.0:
            raise DbbError(f"{{=crop_fill}} {self.crop_fill}: expected 0.2..1")
        if not 0.0 <= self.test_fraction < 1.0:
            raise DbbError(f"{{=test_fraction}} {self.test_fraction}: expected 0 <= f < 1")
        if self.sequence_length < 2:
            raise DbbError("{=sequence_length} must be at least 2 (1 context + 1 predicted frame)")
        self.background.validate()

    def crop_size_for(self, windows_px: np.ndarray, kind: str | None) -> tuple[int, str]:
        """The crop side (pixels) of a capture whose crop windows span ``windows_px`` (N,) source
        pixels, and why: ``crop_size`` if given; for a ``"dynamic"`` object the RSSM's image
        size (it learns at that size, larger crops would only be shrunk again); else as fine
        as the footage (:func:`~dbb_capture.crops.camera.crop_size_for`, up to ``max_crop_size``)."""
        if self.crop_size is not None:
            return self.crop_size, "given"
        if kind == "dynamic":
            return DYNAMIC_CROP_SIZE, "the RSSM's image size, for an object that moves"
        size = crop_size_for(windows_px, self.max_crop_size)
        med = float(np.median(windows_px)) if len(windows_px) else 0.0
        capped = f", capped by the maximum {self.max_crop_size} px" if size == self.max_crop_size and med > size else ""
        return size, f"from the footage: the object's crop window spans {med:.0f} source pixels (median){capped}"


@dataclass
class StageContext:
    """What every stage sees: the inputs, the options and the dataset folder being written."""

    inputs: CaptureInputs
    cfg: PreprocessConfig
    out: Path
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)    # what went wrong but let the run go on


def note_crop_size(ctx: StageContext, size: int, why: str) -> None:
    """Say which crop size the run chose and why (:meth:`PreprocessConfig.crop_size_for`), unless it was given."""
    if why != "given":
        ctx.notes.append(f"crops of {size} px, {why} (--crop-size sets another)")


@dataclass(frozen=True)
class Stage:
    name: str
    run: Callable[[StageContext, Any], Any]
